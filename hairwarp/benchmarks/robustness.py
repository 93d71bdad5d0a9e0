"""Suite ``robustness``: does the hair hold up as a user runs it? Rest, stability grid, convergence in the
substeps, frame-rate steps, head teleports, and MuJoCo's chain and Newton's VBD rod at rest on a collider.

Every figure is measured through the public API only (:class:`hairwarp.Scene`, :class:`hairwarp.runner.Simulation`
with ``advance_frame``, ``guide_curves``, ``frame_stats``, :class:`hairwarp.SimulationFault`), on the shipped scenes
read as raw TOML and changed there, so the suite measures whatever physics the checkout holds.

* :func:`bench_rest` - head held still: guide tip RMS speed per second, from finite differences of the guide points
  between frames (what a cache gives), with the scene's colliders and without them; tips moving > 1 mm in the last
  frame; the largest per-frame motion of vertices resting on a collider.
* :func:`bench_sweep` - ``long_hair`` on its shipped head motion across segments x substeps x links and contacts
  on/off x bend stiffness: fault (its stage), NaN, burst (a vertex faster than 3 m/s) or ok, per cell.
* :func:`bench_convergence` - tips against the 32-substep run as the substeps grow, with and without links; free hair
  and the colliders alone beside them, without a goal, to show where an order is lost.
* :func:`bench_frame_rate` - every shipped scene with links at 2 and 1 substeps against 16.
* :func:`bench_teleport` - a 0.5 m head jump in 1 ms and a 0.5 m move in 2 frames.
* :func:`bench_peers` - MuJoCo's chain (``peers.mujoco_chain_xml`` with capsule geoms) and Newton's VBD rod
  (``add_rod``, shape contacts) at rest on a capsule and on a plane, each in a child process.
* :func:`suite_robustness` - all of them; :func:`md_robustness` its report section.
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import numpy as np

from hairwarp.benchmarks.common import fit_exponent, machine_words, ratboy_assets, run_child
from hairwarp.scene import tomllib  # tomli before Python 3.11

CHART_REST = "bench_robustness_rest.png"
CHART_GRID = "bench_robustness_grid.png"

SCENES = ("tiny", "long_hair", "long_hair_shoulders", "fast_turn", "character", "ratboy_mohawk")

# Goals of hair that holds up: at rest when the head is still, whole at speed, stable at frame rate.
GOAL_REST_MM_S = 2.0  # guide tip RMS speed in the 6th second, head still [mm/s]
GOAL_REST_RATIO = 1.2  # ... and at most this times the same scene without colliders
# Tips slower than this [mm/s] are still, whatever the ratio: 10 um/s is invisible, and float32 coordinates near 1 m
# resolve 0.12 um, 3.6 um/s at 30 fps, so between two still runs the ratio is one of round-off (a groom held as
# drawn, ``groom.hold_shape``, rests at 0.002 mm/s with its colliders and without).
REST_STILL_MM_S = 0.01
# Friction of the rest suite's third run (mu = 4): a vertex that still moves there is not sliding at its cone's edge.
STICKY_FRICTION = 0.8
GOAL_RESTING_MM = 0.05  # largest per-frame motion of a vertex resting on a collider [mm]
MOVING_MM = 1.0  # a tip moving more than this between the last two frames crawls in a render [mm]
# The rest part's fourth and fifth runs: the same still head at this many substeps, frame-rate steps (no goal: the
# goals are at the shipped steps), where links and hair contacts are solved after the free step; the fifth at one step
# a frame
REST_FRAME_RATE_SUBSTEPS = 2
REST_ONE_STEP_SUBSTEPS = 1
BURST_M_S = 3.0  # a vertex faster than this is a burst [m/s]
GOAL_FR2_MM = 25.0  # 2 substeps: tips within this RMS of the 16-substep run, no broken link [mm]
GOAL_FR1_MM = 60.0  # 1 substep: no fault and within this [mm]
GOAL_TELEPORT_M_S = 0.1  # 1 s after a jump, RMS tip speed relative to the head [m/s]
GOAL_ORDER = 1.0  # convergence in the step: at least linear
TELEPORT_M = 0.5
# A vertex rests on a collider when it lies within the collider's contact layer (plus float32 slack) in every frame
# of the last second.
RESTING_SLACK_M = 1.0e-4

#: The extreme motion's scenes: links in the free step (long_hair), links solved by sweeps after it
#: (long_hair_shoulders), links and hair contacts by sweeps (fast_turn).
EXTREME_SCENES = ("long_hair", "long_hair_shoulders", "fast_turn")

SIZES = {
    "full": {
        "rest_scenes": SCENES, "rest_s": 8.0, "rest_second": 6,
        "sweep_segments": (8, 16, 31, 64), "sweep_substeps": (1, 2, 8, 32), "sweep_ei": (1e-7, 2e-4, 1e-2),
        "sweep_s": 1.5,
        "conv_s": 2.0, "conv_substeps": (1, 2, 4, 8, 16), "conv_ref": 32, "conv_overrides": (),
        "conv_finer": (64, 128),
        "fr_scenes": SCENES, "fr_frames": None,
        "teleport_after_s": 1.0, "teleport_overrides": (),
        "extreme_s": 3.0, "extreme_overrides": (), "extreme_scenes": EXTREME_SCENES,
        "peer_s": 8.0,
    },
    "quick": {
        "rest_scenes": ("tiny", "long_hair", "long_hair_shoulders"), "rest_s": 3.0, "rest_second": 3,
        "sweep_segments": (8, 31), "sweep_substeps": (1, 8), "sweep_ei": (2e-4,), "sweep_s": 0.5,
        "conv_s": 1.0, "conv_substeps": (1, 2, 4, 8), "conv_ref": 16, "conv_overrides": ("groom.max_strands=75",),
        "conv_finer": (32,),
        "fr_scenes": ("tiny", "long_hair_shoulders"), "fr_frames": 30,
        "teleport_after_s": 1.0, "teleport_overrides": ("groom.max_strands=75",),
        "extreme_s": 1.0, "extreme_overrides": ("groom.max_strands=75",),
        "extreme_scenes": ("long_hair", "long_hair_shoulders"),
        "peer_s": 3.0,
    },
}


# ---------------------------------------------------------------------------------------------
# scenes as raw TOML


def scene_path(name: str) -> Path:
    from hairwarp.scene import Scene

    return Path(Scene.default_path()).parent / f"{name}.toml"


def missing_assets(name: str) -> str | None:
    """Why a shipped scene cannot run here (its assets are absent), or None."""
    if name == "ratboy_mohawk":
        _, _, skipped = ratboy_assets()
        return skipped["message"] if skipped else None
    return None


def raw_scene(name: str) -> dict:
    """The shipped scene's tables, no dense hair, no preview; the Ratboy's files at the shared assets."""
    raw = tomllib.loads(scene_path(name).read_text())
    raw.setdefault("dense", {})["count"] = 0
    raw["dense"].pop("density", None)
    raw.setdefault("output", {})["preview"] = False
    if name == "ratboy_mohawk":
        groom, body, _ = ratboy_assets()
        raw["groom"]["file"], raw["head"]["file"] = str(groom), str(body)
    return raw


def head_still(raw: dict) -> dict:
    raw = copy.deepcopy(raw)
    raw.setdefault("head", {})["motion"] = {"kind": "still"}
    return raw


def without_colliders(raw: dict) -> dict:
    raw = copy.deepcopy(raw)
    raw.setdefault("head", {})["shape"] = "none"
    raw.pop("colliders", None)
    return raw


def sticky(raw: dict) -> dict:
    """Every collider's friction (the head's and each ``[[colliders]]``'s) at :data:`STICKY_FRICTION`."""
    raw = copy.deepcopy(raw)
    raw.setdefault("head", {})["friction"] = STICKY_FRICTION
    for collider in raw.get("colliders", []):
        collider["friction"] = STICKY_FRICTION
    return raw


def with_links(raw: dict) -> dict:
    """Links on: the scene's own ``[links]``, or the defaults where it has none."""
    raw = copy.deepcopy(raw)
    raw.setdefault("links", {})["enabled"] = True
    return raw


def set_key(raw: dict, path: str, value) -> dict:
    raw = copy.deepcopy(raw)
    *parents, last = path.split(".")
    node = raw
    for p in parents:
        node = node.setdefault(p, {})
    node[last] = value
    return raw


def build(raw: dict, name: str, overrides=()):
    from hairwarp.scene import Scene

    return Scene.from_dict(raw, source=scene_path(name), overrides=list(overrides))


def teleport_available() -> bool:
    from hairwarp.scene import SCHEMA

    return "teleport_distance" in SCHEMA["head"].fields


# ---------------------------------------------------------------------------------------------
# one run


def run_scene(scene, frames: int, *, keep_vertices_from: int | None = None, on_frame=None) -> dict:
    """Simulate ``frames`` frames of ``scene`` through :class:`hairwarp.runner.Simulation`.

    Returns ``{"tips" (F+1, G, 3) float64 from frame 0, "vertices" (frames kept, G, S+1, 3) from
    ``keep_vertices_from``, "fault": None or {"stage", "frame", "message"}, "nan": non-finite guide points without a
    fault, "max_speed" [m/s] (guide velocities, every frame), "broken_links", "broken" (the broken links' indices;
    None without links), "frames_done", "wall_s", "sim"}``.
    """
    import hairwarp as hw
    from hairwarp.runner import Simulation

    t0 = time.perf_counter()
    sim = Simulation(scene)
    G, S = sim.model.strand_count, sim.model.seg_per_strand
    x, _ = sim.guide_curves()
    x = x.reshape(G, S + 1, 3).astype(float)
    tips, kept = [x[:, S].copy()], []
    if keep_vertices_from is not None and keep_vertices_from <= 0:
        kept.append(x)
    fault, nan, vmax, done = None, False, 0.0, 0
    for f in range(1, frames + 1):
        try:
            sim.advance_frame()
        except hw.SimulationFault as exc:
            fault = {"stage": exc.stage, "frame": exc.frame, "bits": exc.bits, "message": str(exc)[:400]}
            break
        x, v = sim.guide_curves()
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            nan = True
            break
        done = f
        vmax = max(vmax, float(np.sqrt((v.astype(float) ** 2).sum(axis=1).max())))
        x = x.reshape(G, S + 1, 3).astype(float)
        tips.append(x[:, S].copy())
        if keep_vertices_from is not None and f >= keep_vertices_from:
            kept.append(x)
        if on_frame is not None:
            on_frame(sim, f)
    stats = sim.frame_stats()
    broken = None if sim.links is None else np.flatnonzero(sim.links.link_broken.numpy())
    return {"tips": np.asarray(tips), "vertices": np.asarray(kept) if kept else None, "fault": fault, "nan": nan,
            "max_speed": vmax, "broken_links": stats.get("broken_links"), "broken": broken, "frames_done": done,
            "wall_s": time.perf_counter() - t0, "sim": sim, "retaken": sim.retaken_frames,
            "retakes": list(sim.retakes)}


def tip_speeds(tips: np.ndarray, frame_dt: float) -> np.ndarray:
    """Per-frame tip speeds (F, G) [m/s] from the positions of consecutive frames."""
    return np.linalg.norm(np.diff(tips, axis=0), axis=-1) / frame_dt


def rms_per_second(speed: np.ndarray, fps: float) -> list[float]:
    """RMS over tips and frames of each whole second [m/s]."""
    n = int(round(fps))
    return [float(np.sqrt(np.mean(speed[k:k + n] ** 2))) for k in range(0, len(speed) - n + 1, n)]


def tip_rms_error(a: np.ndarray, b: np.ndarray) -> float:
    """RMS over frames and guides of the tip distance [m] (the budget suite's measure)."""
    from hairwarp.benchmarks.budget import tip_rms_error as rms

    n = min(len(a), len(b))
    return rms(a[:n], b[:n])


# ---------------------------------------------------------------------------------------------
# 1. rest


def resting_motion(sim, vertices: np.ndarray) -> dict:
    """Vertices (no roots) within a collider's contact layer in every kept frame, and their per-frame motion."""
    cs = sim.collider_set
    if cs is None or vertices is None or len(vertices) < 2:
        return {"vertices": 0, "max_mm": None, "rms_mm": None}
    F, G, V, _ = vertices.shape
    pts = vertices[:, :, 1:].reshape(-1, 3)
    d = cs.signed_distance(pts, sim.head_matrix(sim.stepper.time))[0].reshape(F, G, V - 1, -1)
    layer = np.array([c.thickness for c in cs.colliders], float)
    resting = (d <= layer + RESTING_SLACK_M).any(axis=-1).all(axis=0)
    motion = np.linalg.norm(np.diff(vertices[:, :, 1:], axis=0), axis=-1)[:, resting]
    if not resting.any():
        return {"vertices": 0, "max_mm": None, "rms_mm": None}
    return {"vertices": int(resting.sum()), "max_mm": 1e3 * float(motion.max()),
            "rms_mm": 1e3 * float(np.sqrt(np.mean(motion**2)))}


#: Gravity changes (multiples of :data:`PERTURBATION`) of the rest part's redraws. With the head still, hair whose
#: strands lean on each other settles into one of several nearby states, and which one a run finds moves its speed in
#: the 6th second by tens of per cent with and without colliders alike (the mohawk: 0.12-0.18 mm/s on the head,
#: ratios to the run without colliders 1.00-1.41 over six draws, the same six strands carrying most of the motion
#: in both). The ratio of one pair of runs is then one draw: a scene whose ratio misses the goal runs three more
#: pairs, and the goal is checked on the ratio of the four pairs' means.
REST_REDRAWS = (1.0, -1.0, 2.0)


def rest_redraws(first: tuple[float, float], more: list[tuple[float | None, float | None]]) -> dict:
    """The redraws' figures: second-``s`` speeds [mm/s] with and without colliders of the first pair and of ``more``
    (None where a run faulted or fell short), each pair's ratio, and the ratio of the means (None if a run failed)."""
    pairs = [first, *more]
    ratios = [c / n if c is not None and n else None for c, n in pairs]
    whole = all(c is not None and n for c, n in pairs)
    mean = (sum(c for c, _ in pairs) / sum(n for _, n in pairs)) if whole else None
    return {"perturbations": [0.0, *REST_REDRAWS[:len(more)]], "colliders_mm_s": [c for c, _ in pairs],
            "no_colliders_mm_s": [n for _, n in pairs], "ratios": ratios, "ratio_of_means": mean}


def _rest_second(raw: dict, name: str, duration: float, second: int) -> float | None:
    """Tip RMS speed [mm/s] in second ``second`` of ``raw`` run for ``duration`` s (None if it did not get there)."""
    scene = build(raw, name)
    fps = float(scene.sim.fps)
    run = run_scene(scene, int(round(duration * fps)))
    per_s = rms_per_second(tip_speeds(run["tips"], 1.0 / fps), fps)
    return 1e3 * per_s[second - 1] if not (run["fault"] or run["nan"]) and len(per_s) >= second else None


def bench_rest(scenes=SCENES, duration: float = 8.0, second: int = 6, log=lambda m: None) -> dict:
    """Head still, every scene with and without its colliders for ``duration`` s; figures of the ``second``-th
    second (1-based) and of the last second."""
    rows = []
    for name in scenes:
        why = missing_assets(name)
        if why:
            rows.append({"scene": name, "status": "skipped", "message": why})
            log(f"rest {name}: skipped ({why})")
            continue
        raw = head_still(raw_scene(name))
        row = {"scene": name, "status": "ok"}
        for label, r in (("colliders", raw), ("no_colliders", without_colliders(raw)), ("sticky", sticky(raw)),
                         ("frame_rate", set_key(raw, "sim.substeps", REST_FRAME_RATE_SUBSTEPS)),
                         ("one_step", set_key(raw, "sim.substeps", REST_ONE_STEP_SUBSTEPS))):
            scene = build(r, name)
            fps = float(scene.sim.fps)
            frames = int(round(duration * fps))
            keep = frames - int(round(fps)) if label in ("colliders", "sticky") else None
            run = run_scene(scene, frames, keep_vertices_from=keep)
            speed = tip_speeds(run["tips"], 1.0 / fps)
            per_s = rms_per_second(speed, fps)
            last = np.linalg.norm(run["tips"][-1] - run["tips"][-2], axis=-1) if len(run["tips"]) > 1 else None
            row[label] = {
                "fault": run["fault"], "nan": run["nan"], "frames_done": run["frames_done"], "fps": fps,
                "rms_speed_per_second_mm_s": [1e3 * s for s in per_s],
                "rms_speed_per_frame_mm_s": (1e3 * np.sqrt((speed**2).mean(axis=1))).tolist(),
                "second_mm_s": 1e3 * per_s[second - 1] if len(per_s) >= second else None,
                "moving_tips_fraction": None if last is None else float((last > MOVING_MM * 1e-3).mean()),
                "strands": int(run["tips"].shape[1]), "wall_s": run["wall_s"],
            }
            if label == "colliders":
                row["resting"] = resting_motion(run["sim"], run["vertices"])
            elif label == "sticky":
                row["sticky"]["resting"] = resting_motion(run["sim"], run["vertices"])
        c, n = row["colliders"]["second_mm_s"], row["no_colliders"]["second_mm_s"]
        row["ratio"] = c / n if c is not None and n else None
        row["still"] = c is not None and c <= REST_STILL_MM_S
        if row["ratio"] is not None and row["ratio"] > GOAL_REST_RATIO and not row["still"]:
            more = [(_rest_second(perturbed(raw, k), name, duration, second),
                     _rest_second(without_colliders(perturbed(raw, k)), name, duration, second)) for k in REST_REDRAWS]
            row["redraws"] = rest_redraws((c, n), more)
            log(f"rest {name}: ratio {_f(row['ratio'])} over the goal, redrawn: ratios "
                f"{', '.join(_f(x) for x in row['redraws']['ratios'])}, of the means "
                f"{_f(row['redraws']['ratio_of_means'])}")
        k = row["sticky"]["second_mm_s"]
        row["sticky"]["ratio"] = k / n if k is not None and n else None
        row["meets_speed"] = c is not None and c <= GOAL_REST_MM_S
        judged = row["redraws"]["ratio_of_means"] if row.get("redraws") else row["ratio"]
        row["meets_ratio"] = row["still"] or (judged is not None and judged <= GOAL_REST_RATIO)
        rmax = row["resting"]["max_mm"]
        row["meets_resting"] = rmax is None or rmax < GOAL_RESTING_MM
        rows.append(row)
        fr, one = row["frame_rate"], row["one_step"]
        log(f"rest {name}: second {second} {_f(c)} mm/s (no colliders {_f(n)}), ratio {_f(row['ratio'])}, "
            f"moving tips {_pct(row['colliders']['moving_tips_fraction'])}, resting vertices "
            f"{row['resting']['vertices']} max {_f(rmax)} mm/frame; at {REST_FRAME_RATE_SUBSTEPS} substeps "
            f"{_f(fr['second_mm_s'])} mm/s, moving tips {_pct(fr['moving_tips_fraction'])}; at "
            f"{REST_ONE_STEP_SUBSTEPS} {_f(one['second_mm_s'])} mm/s, moving tips {_pct(one['moving_tips_fraction'])}")
    return {"duration_s": duration, "second": second, "goal_mm_s": GOAL_REST_MM_S, "goal_ratio": GOAL_REST_RATIO,
            "still_mm_s": REST_STILL_MM_S, "sticky_friction": STICKY_FRICTION,
            "goal_resting_mm": GOAL_RESTING_MM, "moving_mm": MOVING_MM, "resting_slack_m": RESTING_SLACK_M,
            "frame_rate_substeps": REST_FRAME_RATE_SUBSTEPS, "one_step_substeps": REST_ONE_STEP_SUBSTEPS, "rows": rows}


# ---------------------------------------------------------------------------------------------
# 2. stability grid


def classify(run: dict) -> str:
    if run["fault"] is not None:
        return "fault"
    if run["nan"]:
        return "nan"
    if run["max_speed"] > BURST_M_S:
        return "burst"
    return "ok"


#: A grid cell whose fastest vertex comes within this share of the burst speed is run again with gravity changed
#: by each of :data:`NEAR_RERUNS` times :data:`PERTURBATION`: hair whipping near the limit crosses it in some runs
#: and not in others, and one run would call it safe. The limp 64 x 1 cell (links and contacts) stayed at 2.45-2.77
#: m/s with gravity changed by 0, +-1e-5 and +2e-5, and faulted at -2e-5 and burst (3.9 m/s) at -3e-5: six reruns.
NEAR_FRACTION = 0.8
NEAR_RERUNS = (1.0, -1.0, 2.0, -2.0, 3.0, -3.0)


def bench_sweep(segments, substeps, stiffness, duration: float, scene_name: str = "long_hair",
                log=lambda m: None) -> dict:
    base = raw_scene(scene_name)
    cells = []
    t0 = time.perf_counter()

    def run_cell(raw):
        scene = build(raw, scene_name)
        return run_scene(scene, int(round(duration * float(scene.sim.fps))))

    for inter in (True, False):
        for ei in stiffness:
            for S in segments:
                for n in substeps:
                    raw = set_key(set_key(set_key(base, "sim.segments", int(S)), "sim.substeps", int(n)),
                                  "strands.bend_stiffness", float(ei))
                    raw = set_key(set_key(raw, "links.enabled", inter), "interactions.enabled", inter)
                    run = run_cell(raw)
                    cell = {"links_contacts": inter, "bend_stiffness": float(ei), "segments": int(S),
                            "substeps": int(n), "status": classify(run), "max_speed_m_s": run["max_speed"],
                            "frames_done": run["frames_done"], "wall_s": round(run["wall_s"], 2),
                            "retaken": run["retaken"], "retakes": run["retakes"],
                            "stage": run["fault"]["stage"] if run["fault"] else None,
                            "fault_frame": run["fault"]["frame"] if run["fault"] else None}
                    if cell["status"] == "ok" and run["max_speed"] > NEAR_FRACTION * BURST_M_S:
                        again = [(times, run_cell(perturbed(raw, times))) for times in NEAR_RERUNS]
                        cell["reruns"] = [{"gravity_change": times * PERTURBATION, "status": classify(r),
                                           "max_speed_m_s": r["max_speed"]} for times, r in again]
                    cells.append(cell)
                    log(f"sweep links+contacts {'on' if inter else 'off'} EI {ei:g} S {S} x {n}: {cell['status']}"
                        + (f" ({cell['stage']}, frame {cell['fault_frame']})" if cell["stage"] else "")
                        + (f", {cell['retaken']} frames taken again" if cell["retaken"] else "")
                        + f", vmax {run['max_speed']:.2f} m/s, {run['wall_s']:.1f} s"
                        + (", again " + ", ".join(f"{r['status']} {r['max_speed_m_s']:.2f}" for r in cell["reruns"])
                           if "reruns" in cell else ""))
    bad = [c for c in cells if c["status"] != "ok"]
    near = [c for c in cells if "reruns" in c]
    near_bad = [c for c in near if any(r["status"] != "ok" for r in c["reruns"])]
    return {"scene": scene_name, "duration_s": duration, "segments": list(segments), "substeps": list(substeps),
            "bend_stiffness": list(stiffness), "burst_m_s": BURST_M_S, "cells": cells,
            "counts": {s: sum(c["status"] == s for c in cells) for s in ("ok", "fault", "nan", "burst")},
            "near_fraction": NEAR_FRACTION, "near": len(near), "near_not_ok": len(near_bad),
            "meets": not bad and not near_bad, "wall_s": time.perf_counter() - t0}


# ---------------------------------------------------------------------------------------------
# 3. convergence


#: Relative change of gravity of the convergence and frame-rate parts' second reference run. Hair in motion amplifies
#: any change (its strands meet, slide off each other and the body one way or another): how far that run's tips and
#: broken links land from the reference's is how closely any run can match it, a floor under the steps' differences.
PERTURBATION = 1.0e-5


def perturbed(raw: dict, times: float = 1.0) -> dict:
    """``raw`` with gravity changed by ``times`` :data:`PERTURBATION` (relative)."""
    gravity = raw.get("sim", {}).get("gravity", [0.0, 0.0, -9.81])
    return set_key(raw, "sim.gravity", [float(g) * (1.0 + times * PERTURBATION) for g in gravity])


def convergence_orders(rows: list[dict]) -> dict:
    """Observed orders of the tip difference in the step: the least-squares ``order`` over every run, the
    ``local_orders`` of each halving of the step and the ``finest_order`` (the last halving). ``meets``: every run
    finished, the fitted order and the finest halving's are both at least :data:`GOAL_ORDER` (a difference that
    flattens out as the step shrinks does not converge, whatever the coarse steps fit)."""
    ok = [row for row in rows if row["fault"] is None and row["tip_rms_mm"]]
    order = fit_exponent([row["dt"] for row in ok], [row["tip_rms_mm"] for row in ok])
    local = [fit_exponent([a["dt"], b["dt"]], [a["tip_rms_mm"], b["tip_rms_mm"]]) for a, b in zip(ok, ok[1:])]
    finest = local[-1] if local else None
    return {"order": order, "local_orders": local, "finest_order": finest,
            "meets": (order is not None and order >= GOAL_ORDER and finest is not None and finest >= GOAL_ORDER
                      and len(ok) == len(rows))}


#: The worst strands whose share of the tip difference :func:`strand_spread` reports.
WORST_STRANDS = 10


def strand_spread(tips: np.ndarray, reference: np.ndarray) -> dict:
    """How the tip difference to ``reference`` spreads over the strands: the median strand's RMS over frames [mm] and
    the share of the mean square that the :data:`WORST_STRANDS` worst strands carry (a few strands that settle on
    another side of a collider or of their neighbours dominate an RMS over all)."""
    n = min(len(tips), len(reference))
    per = np.sqrt(np.mean(np.sum((tips[:n] - reference[:n]) ** 2, axis=-1), axis=0))  # (G,)
    square = per ** 2
    total = float(square.sum())
    worst = float(np.sort(square)[::-1][:WORST_STRANDS].sum())
    return {"median_strand_mm": 1e3 * float(np.median(per)), "worst_share": worst / total if total > 0 else 0.0}


def convergence_variants(base: dict) -> dict:
    """label -> (scene tables, whether the goal applies) of :func:`bench_convergence`: the scene with and without
    its links (the goal), and two without a goal that say where an order is lost: *free hair* (no links, hair contacts
    or colliders: the integrator's own order) and *colliders only* (the scene's colliders, no links or hair
    contacts)."""
    no_links = set_key(base, "links.enabled", False)
    alone = set_key(no_links, "interactions.enabled", False)
    return {"links": (set_key(base, "links.enabled", True), True), "no links": (no_links, True),
            "free hair": (without_colliders(alone), False), "colliders only": (alone, False)}


def successive_differences(runs: dict) -> list[dict]:
    """Each run's tips against the next finer run's (``runs``: substeps -> :func:`run_scene` result), coarse to fine:
    ``{"substeps": (n, m), "tip_rms_mm", "median_strand_mm"}``, None past a fault. A method of order p divides these by
    2^p at each halving of the step, whatever the finest run; the differences to one reference divide by 2^p + 1 at
    the halving next to it (3 in a first-order method: an "order" of 1.58)."""
    out = []
    steps = sorted(runs)
    for n, m in zip(steps, steps[1:]):
        a, b = runs[n], runs[m]
        ok = a["fault"] is None and b["fault"] is None
        out.append({"substeps": [n, m], "tip_rms_mm": 1e3 * tip_rms_error(a["tips"], b["tips"]) if ok else None,
                    "median_strand_mm": strand_spread(a["tips"], b["tips"])["median_strand_mm"] if ok else None})
    return out


def halving_orders(values: list) -> list:
    """``log2`` of each ratio of consecutive values (the order of each halving), None where one is missing."""
    return [math.log2(a / b) if a and b else None for a, b in zip(values, values[1:])]


#: Relative changes of gravity of the convergence part's sensitivity runs (besides :data:`PERTURBATION`): the reference
#: run's tips respond to a change of any source, the step's error being one; the size of their response against the
#: change's is the scene's own order, which no step can beat.
SENSITIVITY = (1.0e-3, 1.0e-2)


def bench_convergence(substeps, ref: int, duration: float, overrides=(), scene_name: str = "long_hair",
                      finer=(), log=lambda m: None) -> dict:
    base = raw_scene(scene_name)
    variants = {}
    for label, (raw, goal) in convergence_variants(base).items():
        runs = {}
        for n in (ref, *substeps, *finer):
            scene = build(set_key(raw, "sim.substeps", int(n)), scene_name, overrides)
            runs[n] = run_scene(scene, int(round(duration * float(scene.sim.fps))))
        reference = runs[ref]
        frames = len(reference["tips"]) - 1
        changes = (PERTURBATION, *SENSITIVITY)
        again = {c: run_scene(build(set_key(perturbed(raw, c / PERTURBATION), "sim.substeps", int(ref)), scene_name,
                                    overrides), frames) for c in changes}
        strands = int(reference["tips"].shape[1])
        rows = []
        for n in substeps:
            r = runs[n]
            err = tip_rms_error(r["tips"], reference["tips"]) if reference["fault"] is None else None
            spread = strand_spread(r["tips"], reference["tips"]) if err is not None else {}
            end = np.linalg.norm(r["tips"][-1] - reference["tips"][min(len(r["tips"]), len(reference["tips"])) - 1],
                                 axis=-1)
            rows.append({"substeps": n, "dt": 1.0 / (float(scene.sim.fps) * n), "fault": r["fault"],
                         "tip_rms_mm": None if err is None else 1e3 * err,
                         "strands_over_50mm_at_end": int((end > 0.05).sum()), "wall_s": r["wall_s"], **spread})
        sensitivity = [{"gravity_change": c,
                        "tip_rms_mm": (1e3 * tip_rms_error(again[c]["tips"], reference["tips"])
                                       if reference["fault"] is None and again[c]["fault"] is None else None)}
                       for c in changes]
        orders = convergence_orders(rows)
        successive = successive_differences(runs)
        successive_orders = halving_orders([d["tip_rms_mm"] for d in successive])
        # the finest halving of the differences between successive runs too: against the reference alone a first-order
        # method's finest halving reads 1.58
        last = successive_orders[-1] if successive_orders else None
        orders["meets"] = bool(orders["meets"] and last is not None and last >= GOAL_ORDER) if goal else None
        variants[label] = {"rows": rows, "reference_fault": reference["fault"],
                           "reference_again_mm": sensitivity[0]["tip_rms_mm"], **orders,
                           "median_order": fit_exponent([row["dt"] for row in rows if row.get("median_strand_mm")],
                                                        [row["median_strand_mm"] for row in rows
                                                         if row.get("median_strand_mm")]),
                           "successive": successive,
                           "successive_orders": successive_orders,
                           "successive_median_orders": halving_orders([d["median_strand_mm"] for d in successive]),
                           "sensitivity": sensitivity,
                           "sensitivity_order": fit_exponent([c["gravity_change"] for c in sensitivity],
                                                             [c["tip_rms_mm"] for c in sensitivity])}
        log(f"convergence {label}: " + ", ".join(f"{row['substeps']}: {_f(row['tip_rms_mm'])} mm" for row in rows)
            + f", order {_f(variants[label]['order'])}, finest halving {_f(variants[label]['finest_order'])}, "
            f"{ref} again {_f(sensitivity[0]['tip_rms_mm'])} mm; successive "
            + ", ".join(f"{d['substeps'][0]}-{d['substeps'][1]} {_f(d['tip_rms_mm'])}" for d in successive)
            + " mm; gravity changed by " + ", ".join(f"{c['gravity_change']:g}: {_f(c['tip_rms_mm'])}"
                                                      for c in sensitivity) + " mm")
    return {"scene": scene_name, "duration_s": duration, "reference_substeps": ref, "overrides": list(overrides),
            "goal_order": GOAL_ORDER, "perturbation": PERTURBATION, "strands": strands, "finer": list(finer),
            "variants": variants}


# ---------------------------------------------------------------------------------------------
# 4. frame rate


#: Substeps between the shipped 8 and frame rate that the frame-rate part also runs, without a goal: where a form of
#: the interactions hands over to another (``response = "auto"``), a hole between them shows here (at 4 substeps the
#: finer-step forms once broke 2,583 of the mohawk's links).
INTERMEDIATE_SUBSTEPS = (4,)


def bench_frame_rate(scenes=SCENES, frames=None, log=lambda m: None) -> dict:
    rows = []
    for name in scenes:
        why = missing_assets(name)
        if why:
            rows.append({"scene": name, "status": "skipped", "message": why})
            continue
        raw = with_links(raw_scene(name))
        runs = {}
        for n in (16, *INTERMEDIATE_SUBSTEPS, 2, 1):
            scene = build(set_key(raw, "sim.substeps", n), name)
            runs[n] = run_scene(scene, int(frames or scene.sim.frames))
        again = run_scene(build(set_key(perturbed(raw), "sim.substeps", 16), name), int(frames or scene.sim.frames))
        row = {"scene": name, "status": "ok", "links_shipped": bool(raw_scene(name).get("links", {}).get("enabled")),
               "frames": int(frames or scene.sim.frames), "reference_fault": runs[16]["fault"],
               "reference_again": {"fault": again["fault"], "broken_links": again["broken_links"],
                                   "tip_rms_mm": 1e3 * tip_rms_error(again["tips"], runs[16]["tips"])}}
        # links that break in either reference run break with the motion; the others break with the step
        moved = set() if runs[16]["broken"] is None else {*runs[16]["broken"].tolist(), *again["broken"].tolist()}
        for n in (*INTERMEDIATE_SUBSTEPS, 2, 1):
            r = runs[n]
            row[str(n)] = {"fault": r["fault"], "nan": r["nan"], "broken_links": r["broken_links"],
                           "step_broken_links": None if r["broken"] is None else len(set(r["broken"].tolist()) - moved),
                           "reference_broken_links": runs[16]["broken_links"], "frames_done": r["frames_done"],
                           "tip_rms_mm": 1e3 * tip_rms_error(r["tips"], runs[16]["tips"]),
                           "max_speed_m_s": r["max_speed"], "wall_s": r["wall_s"],
                           "refined_frames": r["sim"].refined_frames, "retaken_frames": r["retaken"]}
        two, one = row["2"], row["1"]
        two["meets"] = two["fault"] is None and not two["nan"] and not two["broken_links"] and \
            two["tip_rms_mm"] <= GOAL_FR2_MM
        one["meets"] = one["fault"] is None and not one["nan"] and one["tip_rms_mm"] <= GOAL_FR1_MM
        rows.append(row)
        mid = "; ".join(f"{n} substeps {_fault(row[str(n)])} broken {row[str(n)]['broken_links']}"
                        for n in INTERMEDIATE_SUBSTEPS)
        log(f"frame rate {name}: {mid}; 2 substeps {_fault(two)} broken {two['broken_links']} tips "
            f"{_f(two['tip_rms_mm'])} mm ({two['refined_frames']} frames taken again, {two['retaken_frames']} after "
            f"a fault or a whip); 1 substep {_fault(one)} broken {one['broken_links']} tips {_f(one['tip_rms_mm'])} mm "
            f"({one['refined_frames']} taken again, {one['retaken_frames']} after a fault or a whip)")
    return {"reference_substeps": 16, "goal_2_mm": GOAL_FR2_MM, "goal_1_mm": GOAL_FR1_MM, "perturbation": PERTURBATION,
            "rows": rows}


# ---------------------------------------------------------------------------------------------
# 5. teleport


def jump_keys(t0: float, span: float, distance: float = TELEPORT_M) -> list[dict]:
    return [{"time": t0, "translate": [0.0, 0.0, 0.0]}, {"time": t0 + span, "translate": [distance, 0.0, 0.0]}]


def relative_tip_speed(sim, tips_a, tips_b, t_a: float, t_b: float) -> float:
    """RMS speed [m/s] of tips in the head's frame between two frames: tip velocity less the head's rigid
    velocity at the tip."""
    def local(x, t):
        m = sim.head_matrix(t)
        return (x - m[:3, 3]) @ m[:3, :3]

    return float(np.sqrt(np.mean(np.sum((local(tips_b, t_b) - local(tips_a, t_a)) ** 2, axis=-1)))) / (t_b - t_a)


def bench_teleport(after_s: float = 1.0, overrides=(), scene_name: str = "long_hair", log=lambda m: None) -> dict:
    base = raw_scene(scene_name)
    fps = float(base["sim"].get("fps", 30.0))
    t0 = 0.5
    cases = {"teleport (1 ms)": 1.0e-3, "move in 2 frames": 2.0 / fps}
    available = teleport_available()
    settings = [None, 0.2] if available else [None]
    rows = []
    for label, span in cases.items():
        for td in settings:
            raw = copy.deepcopy(base)
            raw["head"]["motion"] = {"kind": "keyframes", "keys": jump_keys(t0, span)}
            if td is not None:
                raw["head"]["teleport_distance"] = td
            scene = build(raw, scene_name, overrides)
            t_end = t0 + span
            k = int(math.ceil((t_end + after_s) * fps))
            run = run_scene(scene, k)
            speed = None
            if run["fault"] is None and not run["nan"]:
                speed = relative_tip_speed(run["sim"], run["tips"][k - 1], run["tips"][k], (k - 1) / fps, k / fps)
            row = {"case": label, "span_s": span, "distance_m": TELEPORT_M, "teleport_distance": td,
                   "fault": run["fault"], "nan": run["nan"], "frames_done": run["frames_done"],
                   "measured_at_s": k / fps, "relative_tip_rms_m_s": speed, "max_speed_m_s": run["max_speed"],
                   "meets": speed is not None and speed <= GOAL_TELEPORT_M_S, "wall_s": run["wall_s"]}
            rows.append(row)
            log(f"teleport {label}, teleport_distance {td}: {_fault(row)}, tips {_f(speed)} m/s 1 s after")
    return {"scene": scene_name, "overrides": list(overrides), "jump_at_s": t0, "after_s": after_s,
            "goal_m_s": GOAL_TELEPORT_M_S, "teleport_distance_available": available, "rows": rows}


# ---------------------------------------------------------------------------------------------
# 5b. extreme motion: a spinning head, a turn ten times the shipped speed

SPIN_REV_S = 3.0  # spins per second
TURN_FACTOR = 10.0  # the shipped turn's speed, times this
EXTREME_REFERENCE_SUBSTEPS = 32  # the as-shipped runs once more at these, for the speed a fine step gives


def spin_keys(start: float, duration: float, revs_per_s: float) -> list[dict]:
    """Keyframes of a head that spins about z at ``revs_per_s`` from ``start`` for ``duration`` s: a key every
    20 degrees (consecutive keys under 180 degrees apart), the angle wrapped to (-180, 180]."""
    step = 20.0
    n = int(math.ceil(duration * revs_per_s * 360.0 / step))
    keys = []
    for i in range(n + 1):
        angle = (i * step + 180.0) % 360.0 - 180.0
        keys.append({"time": start + i * step / (360.0 * revs_per_s), "axis": [0.0, 0.0, 1.0], "angle_deg": angle})
    return keys


def faster_motion(motion: dict, factor: float) -> dict:
    """A scene's ``[head.motion]`` table played ``factor`` times faster: keyframes at their times over ``factor``,
    a periodic motion (turn, nod, shake) with its period over ``factor``."""
    if motion.get("kind") == "keyframes":
        return dict(motion, keys=[dict(key, time=float(key["time"]) / factor) for key in motion["keys"]])
    return dict(motion, period=float(motion.get("period", 1.5)) / factor)


def bench_extreme(duration: float, overrides=(), scene_name: str = "long_hair", log=lambda m: None) -> dict:
    """The shipped scene at its substeps, links, contacts and colliders, on a head spinning at SPIN_REV_S and on its
    own motion TURN_FACTOR times faster (:func:`faster_motion`); and each without links, contacts and colliders
    (free hair). Goal: no fault, no NaN."""
    base = raw_scene(scene_name)
    fps = float(base["sim"].get("fps", 30.0))
    motion = dict(base["head"]["motion"])
    spin = {"kind": "keyframes", "keys": spin_keys(0.2, duration, SPIN_REV_S), "pivot": motion.get("pivot")}
    fast = faster_motion(motion, TURN_FACTOR)
    rows = []
    for label, mot in ((f"spin {SPIN_REV_S:g} rev/s", spin), (f"motion {TURN_FACTOR:g}x the shipped speed", fast)):
        for free in (False, True):
            raw = copy.deepcopy(base)
            raw["head"]["motion"] = {k: v for k, v in mot.items() if v is not None}
            if free:
                raw["head"]["shape"] = "none"
                raw.pop("colliders", None)
                raw.setdefault("links", {})["enabled"] = False
                raw.setdefault("interactions", {})["enabled"] = False
            frames = int(round(duration * fps))
            run = run_scene(build(raw, scene_name, overrides), frames)
            row = {"case": label, "free": free, "fault": run["fault"], "nan": run["nan"],
                   "frames_done": run["frames_done"], "max_speed_m_s": run["max_speed"],
                   "broken_links": run["broken_links"], "meets": run["fault"] is None and not run["nan"],
                   "retaken": run["retaken"], "retakes": run["retakes"], "wall_s": run["wall_s"]}
            if not free:  # what finer steps give: a longer step whips linked hair harder on motion this fast
                fine = run_scene(build(raw, scene_name, [*overrides, f"sim.substeps={EXTREME_REFERENCE_SUBSTEPS}"]),
                                 frames)
                row["fine"] = {"substeps": EXTREME_REFERENCE_SUBSTEPS, "fault": fine["fault"],
                               "max_speed_m_s": fine["max_speed"], "broken_links": fine["broken_links"],
                               "wall_s": fine["wall_s"]}
            rows.append(row)
            log(f"extreme {label}{' (free hair)' if free else ''}: {_fault(row)}, vmax {_f(run['max_speed'])} m/s"
                + (f", frames taken again: {run['retaken']}" if run["retaken"] else "")
                + (f"; at {EXTREME_REFERENCE_SUBSTEPS} substeps {_f(row['fine']['max_speed_m_s'])} m/s, "
                   f"{row['fine']['broken_links']} links broken" if "fine" in row else ""))
    return {"scene": scene_name, "overrides": list(overrides), "duration_s": duration, "rows": rows}


# ---------------------------------------------------------------------------------------------
# 6. peers: MuJoCo's chain and Newton's VBD rod at rest on a collider (child processes)

PEER_SEGMENTS = 20
PEER_EI = 2.0e-4  # the shipped scenes' bend stiffness [N m^2]
PEER_HAIR_DAMPING = 2.0e-7  # [N m^2 s]
PEER_DT = 1.0 / 240.0  # the shipped scenes' step (8 substeps at 30 fps)
PEER_FPS = 30.0
# A capsule along y under the strand released from the canonical 80 degree tilt, so the strand drapes over it; or a
# floor 0.25 m under the root, so the last 5 cm of the 0.3 m strand lie on it.
PEER_CAPSULE = {"center": (-0.15, 0.0, -0.08), "radius": 0.05, "half_length": 0.2}
PEER_FLOOR_Z = -0.25
# Newton's VBD rod: the iterations of the stability suite's runs, a contact stiffness that keeps the rod's surface
# within a fraction of its radius of the collider's, and a detection gap above the rod's travel in a step.
PEER_NEWTON_ITERATIONS = 10
PEER_NEWTON_CONTACT_KE = 1.0e4  # [N/m]
PEER_NEWTON_GAP = 0.01  # [m]


def _mujoco_rest_xml(collider: str, contact: bool) -> str:
    from hairwarp.benchmarks.common import RADIUS, STRAND_LENGTH
    from hairwarp.benchmarks.peers import mujoco_chain_xml

    S = PEER_SEGMENTS
    L = STRAND_LENGTH / S
    xml = mujoco_chain_xml(S, integrator="discrete", dt=PEER_DT, damping=PEER_HAIR_DAMPING / L,
                           stiffness=[PEER_EI / L] * S)
    # a capsule geom on every segment (inertials stay explicit: inertiafromgeom is false)
    geom = f"<geom type='capsule' size='{RADIUS!r}' fromto='0 0 0 0 0 {-L!r}' friction='0.5 0.005 0.0001'/>"
    xml = xml.replace("<inertial ", geom + "<inertial ")
    if collider == "capsule":
        c = PEER_CAPSULE
        body = (f"<geom type='capsule' size='{c['radius']!r} {c['half_length']!r}' pos='{c['center'][0]!r} "
                f"{c['center'][1]!r} {c['center'][2]!r}' euler='1.5707963 0 0' friction='0.5 0.005 0.0001'/>")
    else:
        body = f"<geom type='plane' size='1 1 0.01' pos='0 0 {PEER_FLOOR_Z!r}' friction='0.5 0.005 0.0001'/>"
    xml = xml.replace("<worldbody>", "<worldbody>" + body)
    flag = "<flag energy='enable'/>" if contact else "<flag contact='disable' energy='enable'/>"
    return xml.replace("<flag contact='disable' energy='enable'/>", flag)


def _mujoco_points(m, d, S: int) -> np.ndarray:
    """Joint positions and the tip of the chain (S+1, 3)."""
    import mujoco

    from hairwarp.benchmarks.common import STRAND_LENGTH

    mujoco.mj_kinematics(m, d)
    pts = [np.array(d.xpos[k]) for k in range(1, S + 1)]
    R = np.array(d.xmat[S]).reshape(3, 3)
    pts.append(d.xpos[S] + R @ np.array([0.0, 0.0, -STRAND_LENGTH / S]))
    return np.asarray(pts)


def _collider_distance(collider: str, pts: np.ndarray) -> np.ndarray:
    if collider == "capsule":
        c = PEER_CAPSULE
        rel = pts - np.asarray(c["center"])
        rel[:, 1] -= np.clip(rel[:, 1], -c["half_length"], c["half_length"])
        return np.linalg.norm(rel, axis=-1) - c["radius"]
    return pts[:, 2] - PEER_FLOOR_Z


def _peer_rest_record(pts: np.ndarray, collider: str, contact: bool) -> dict:
    """A peer's strand at rest from its points (frames, S+1, 3) sampled at PEER_FPS: whether they stayed finite, the
    tip's RMS speed per second and per frame [mm/s]; with ``contact`` the points within the strand's radius + 1 mm
    of the collider in every frame of the last second (the root left out) and their largest motion a frame [mm]."""
    from hairwarp.benchmarks.common import RADIUS

    finite = bool(np.isfinite(pts).all())
    speed = tip_speeds(pts[:, -1:, :], 1.0 / PEER_FPS)
    rec = {"finite": finite, "rms_speed_per_second_mm_s": [1e3 * s for s in rms_per_second(speed, PEER_FPS)],
           "rms_speed_per_frame_mm_s": (1e3 * speed[:, 0]).tolist()}
    if contact:
        window = pts[-int(PEER_FPS) - 1:]
        dist = np.stack([_collider_distance(collider, p) for p in window])
        resting = (dist <= RADIUS + 1.0e-3).all(axis=0)
        resting[0] = False  # the root
        motion = np.linalg.norm(np.diff(window, axis=0), axis=-1)[:, resting]
        rec["resting"] = {"points": int(resting.sum()),
                          "max_mm": 1e3 * float(motion.max()) if resting.any() and finite else None}
    return rec


def mujoco_rest(req: dict) -> dict:
    """MuJoCo chain released from the canonical tilt onto a static collider, ``duration`` s at 1/240 s with
    ``discrete`` (MuJoCo 4: joint springs implicit): tip RMS speed per second from 30 fps samples, with contacts
    and without; the largest per-frame motion of points within the chain's radius + 1 mm of the collider over the
    last second."""
    import mujoco

    from hairwarp.benchmarks.common import TILT_DEG
    from hairwarp.benchmarks.peers import mujoco_set_tilt

    S = PEER_SEGMENTS
    duration = float(req["duration"])
    per_frame = int(round(1.0 / (PEER_FPS * PEER_DT)))
    frames = int(round(duration * PEER_FPS))
    out = {}
    for collider in ("capsule", "plane"):
        entry = {}
        for label, contact in (("contact", True), ("no_contact", False)):
            m = mujoco.MjModel.from_xml_string(_mujoco_rest_xml(collider, contact))
            d = mujoco.MjData(m)
            mujoco_set_tilt(m, d, TILT_DEG)
            pts = [_mujoco_points(m, d, S)]
            for _ in range(frames):
                mujoco.mj_step(m, d, nstep=per_frame)
                pts.append(_mujoco_points(m, d, S))
            rec = _peer_rest_record(np.asarray(pts), collider, contact)
            rec["unstable_warning"] = int(d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)
            entry[label] = rec
        out[collider] = entry
    return {"mujoco": mujoco.__version__, "segments": S, "dt": PEER_DT, "integrator": "discrete",
            "bend_stiffness": PEER_EI, "duration_s": duration, "results": out}


def _newton_rest_model(collider: str, contact: bool):
    """Newton's VBD rod of the peers' strand hanging straight down from the origin (``add_rod``, bend and twist
    stiffness EI / L [N m/rad] and damping PEER_HAIR_DAMPING / L [N m s/rad] at every joint, the cylinder mass
    properties), its root a rod joint to the world with the same spring, and the collider a static shape where
    MuJoCo's XML places it. Returns the model and the rod's body indices (body origin at the segment's centre, local
    +z from root to tip)."""
    import newton
    import warp as wp

    from hairwarp.benchmarks.common import DENSITY, GRAVITY, RADIUS, STRAND_LENGTH, straight_strands
    from hairwarp.benchmarks.peers import _cylinder_bodies

    S = PEER_SEGMENTS
    L = STRAND_LENGTH / S
    k, kd = PEER_EI / L, PEER_HAIR_DAMPING / L
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
    # MuJoCo's sliding friction; its torsional and rolling coefficients are Newton's defaults
    cfg = newton.ModelBuilder.ShapeConfig(density=DENSITY, ke=PEER_NEWTON_CONTACT_KE, mu=0.5, gap=PEER_NEWTON_GAP,
                                          has_shape_collision=contact, has_particle_collision=False)
    verts = straight_strands(np.zeros((1, 3)), S, np.array([0.0, 0.0, -1.0]))
    rod = newton.Rod([wp.vec3(*p) for p in verts[0]], radius=RADIUS)
    bodies, joints = builder.add_rod(rod=rod, cfg=cfg, stretch_stiffness=1.0e5, stretch_damping=0.0,
                                     bend_stiffness=k, bend_damping=kd, twist_stiffness=k, twist_damping=kd,
                                     wrap_in_articulation=False)
    _cylinder_bodies(builder, bodies, S)
    # The root: a rod joint to the world at the origin, its world anchor's +z pointing down, so that its spring rests
    # with the strand hanging straight down, as the spring of MuJoCo's root ball joint.
    down = wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), math.pi)
    root = builder.add_joint_rod(parent=-1, child=bodies[0], parent_xform=wp.transform(wp.vec3(0.0, 0.0, 0.0), down),
                                 child_xform=wp.transform(wp.vec3(0.0, 0.0, -L / 2), wp.quat_identity()),
                                 stretch_stiffness=1.0e5, stretch_damping=0.0, bend_stiffness=k, bend_damping=kd,
                                 twist_stiffness=k, twist_damping=kd)
    builder.add_articulation([*joints, root])
    if collider == "capsule":
        c = PEER_CAPSULE
        # along y: MuJoCo's euler='1.5707963 0 0' turns the capsule's z axis about x
        turn = wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), 1.5707963)
        builder.add_shape_capsule(-1, xform=wp.transform(wp.vec3(*c["center"]), turn), radius=c["radius"],
                                  half_height=c["half_length"], cfg=cfg)
    else:
        builder.add_ground_plane(height=PEER_FLOOR_Z, cfg=cfg)
    builder.color()
    return builder.finalize(device="cpu"), bodies


def _newton_points(body_q: np.ndarray, L: float) -> np.ndarray:
    """Joint positions and the tip of the rod (S+1, 3) from its bodies' poses (S, 7)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(body_q, np.float64)
    half = Rotation.from_quat(q[:, 3:]).apply([0.0, 0.0, L / 2])
    return np.concatenate([q[:, :3] - half, q[-1:, :3] + half[-1:]])


def newton_rest(req: dict) -> dict:
    """Newton's VBD rod (:func:`_newton_rest_model`) released from the canonical tilt onto a static collider (each of
    ``req["colliders"]``, default the capsule and the plane),
    ``duration`` s at 1/240 s with PEER_NEWTON_ITERATIONS iterations, shape contacts from ``CollisionPipeline``
    passed to ``SolverVBD.step``: the outputs of :func:`mujoco_rest`, with contacts and without (no collision
    pipeline, the collider's shape not colliding); plus the smallest clearance between the rod's surface and the
    collider over the run (negative: inside)."""
    import newton
    import warp as wp
    from scipy.spatial.transform import Rotation

    from hairwarp.benchmarks.common import RADIUS, STRAND_LENGTH, TILT_DEG

    wp.config.quiet = True
    S = PEER_SEGMENTS
    L = STRAND_LENGTH / S
    duration = float(req["duration"])
    per_frame = int(round(1.0 / (PEER_FPS * PEER_DT)))
    frames = int(round(duration * PEER_FPS))
    turn = Rotation.from_rotvec([0.0, math.radians(TILT_DEG), 0.0])
    out = {}
    for collider in req.get("colliders", ("capsule", "plane")):
        entry = {}
        for label, contact in (("contact", True), ("no_contact", False)):
            model, bodies = _newton_rest_model(collider, contact)
            solver = newton.solvers.SolverVBD(model, iterations=PEER_NEWTON_ITERATIONS)
            pipeline = newton.CollisionPipeline(model) if contact else None
            contacts = pipeline.contacts() if contact else None
            states = [model.state(), model.state()]
            control = model.control()
            # released turned TILT_DEG about the root, at rest
            q = states[0].body_q.numpy().astype(np.float64)
            q[:, :3] = turn.apply(q[:, :3])
            q[:, 3:] = (turn * Rotation.from_quat(q[:, 3:])).as_quat()
            for s in states:
                s.body_q.assign(q.astype(np.float32))
            pts = [_newton_points(q[bodies], L)]
            for _ in range(frames):
                for _ in range(per_frame):
                    states[0].clear_forces()
                    if contact:
                        pipeline.collide(states[0], contacts)
                    solver.step(states[0], states[1], control, contacts, PEER_DT)
                    states[0], states[1] = states[1], states[0]
                pts.append(_newton_points(states[0].body_q.numpy()[bodies], L))
                if not np.isfinite(pts[-1]).all():
                    break
            pts = np.asarray(pts)
            rec = _peer_rest_record(pts, collider, contact)
            clearance = min(float(_collider_distance(collider, p).min()) for p in pts) - RADIUS
            rec.update(frames_done=len(pts) - 1, min_clearance_mm=1e3 * clearance if rec["finite"] else None)
            entry[label] = rec
        out[collider] = entry
    return {"newton": newton.__version__, "segments": S, "dt": PEER_DT, "solver": "SolverVBD",
            "iterations": PEER_NEWTON_ITERATIONS, "bend_stiffness": PEER_EI,
            "contact_stiffness": PEER_NEWTON_CONTACT_KE, "duration_s": duration, "results": out}


def _second_figures(r: dict, second: int) -> None:
    """Add the tip speed of ``second`` with contacts and without, and their ratio, to each collider of a peer's
    at-rest result."""
    if r.get("status") != "ok":
        return
    for entry in r["results"].values():
        c = entry["contact"]["rms_speed_per_second_mm_s"]
        n = entry["no_contact"]["rms_speed_per_second_mm_s"]
        entry["second_mm_s"] = c[second - 1] if len(c) >= second else None
        entry["no_contact_second_mm_s"] = n[second - 1] if len(n) >= second else None
        entry["ratio"] = (entry["second_mm_s"] / entry["no_contact_second_mm_s"]
                          if entry["second_mm_s"] is not None and entry["no_contact_second_mm_s"] else None)


def bench_peers(duration: float, second: int, timeout_s: float = 240.0) -> dict:
    r = run_child({"kind": "robustness_mujoco_rest", "duration": duration}, timeout_s)
    nw = run_child({"kind": "robustness_newton_rest", "duration": duration}, timeout_s)
    _second_figures(r, second)
    _second_figures(nw, second)
    not_modelled = {
        "mujoco": "sweep, frame rate and teleport: the chain of peers.py is one strand without static links, hair "
                  "contacts or a groom on a head, so the long_hair cases have no counterpart there; how large a step "
                  "the chain itself takes is the stability suite's map (section 3: the largest stable step per bend "
                  "stiffness, Euler, implicitfast and discrete against hairwarp's integrators)",
        "newton": "sweep, frame rate and teleport, as for MuJoCo: one VBD rod, no links, hair contacts or groom; the "
                  "rod's largest stable step per bend stiffness is on the same map (section 3)",
    }
    return {"mujoco_rest": r, "newton_rest": nw, "second": second, "not_modelled": not_modelled}


# ---------------------------------------------------------------------------------------------
# charts


def chart_rest(rest: dict, peers: dict | None, path) -> Path:
    from hairwarp.benchmarks.report import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 5))
    colors = plt.cm.tab10.colors
    n = 0
    for row in rest["rows"]:
        if row.get("status") != "ok":
            continue
        for label, ls in (("colliders", "-"), ("no_colliders", "--")):
            r = row[label]
            y = np.maximum(np.asarray(r["rms_speed_per_frame_mm_s"]), 1e-4)
            t = (np.arange(len(y)) + 1) / r["fps"]
            ax.plot(t, y, ls=ls, color=colors[n % 10], lw=1.1 if ls == "-" else 0.9,
                    label=f"{row['scene']}" + (" (colliders)" if label == "colliders" else " (no colliders)"))
        n += 1
    for key, name in (("mujoco_rest", "MuJoCo chain"), ("newton_rest", "Newton VBD rod")):
        pr = (peers or {}).get(key, {})
        if pr.get("status") != "ok":
            continue
        for collider, entry in pr["results"].items():
            y = np.maximum(np.asarray(entry["contact"]["rms_speed_per_frame_mm_s"]), 1e-4)
            ax.plot((np.arange(len(y)) + 1) / PEER_FPS, y, ls=":", color=colors[n % 10], lw=1.0,
                    label=f"{name} on a {collider}")
            n += 1
    ax.axhline(GOAL_REST_MM_S, color="k", lw=0.8, ls="-.", label=f"goal {GOAL_REST_MM_S:g} mm/s")
    s = rest["second"]
    ax.axvspan(s - 1, s, color="0.9", zorder=0)
    ax.set_yscale("log")
    ax.set_xlabel("time [s] (head still; shaded: the second the goal reads)")
    ax.set_ylabel("guide tip RMS speed per frame [mm/s]")
    ax.set_title("Rest: tip speed with the head still, with colliders (solid) and without (dashed)", fontsize=10)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


_STATUS_COLOR = {"ok": "#4caf50", "burst": "#ff9800", "nan": "#9c27b0", "fault": "#e53935"}


def chart_grid(sweep: dict, path) -> Path:
    from matplotlib.patches import Patch

    from hairwarp.benchmarks.report import _pyplot

    plt = _pyplot()
    eis, segs, subs = sweep["bend_stiffness"], sweep["segments"], sweep["substeps"]
    fig, axes = plt.subplots(2, len(eis), figsize=(3.3 * len(eis) + 0.6, 6.4), squeeze=False)
    by = {(c["links_contacts"], c["bend_stiffness"], c["segments"], c["substeps"]): c for c in sweep["cells"]}
    for i, inter in enumerate((True, False)):
        for j, ei in enumerate(eis):
            ax = axes[i][j]
            ax.grid(False)
            for a, S in enumerate(segs):
                for b, n in enumerate(subs):
                    c = by.get((inter, ei, S, n))
                    color = _STATUS_COLOR.get(c["status"], "0.8") if c else "0.85"
                    retaken = c.get("retaken", 0) if c else 0
                    ax.add_patch(plt.Rectangle((b, a), 1, 1, color=color, ec="white", lw=1.5))
                    if retaken and c["status"] == "ok":
                        ax.add_patch(plt.Rectangle((b + 0.03, a + 0.03), 0.94, 0.94, fill=False, hatch="///",
                                                   ec="0.35", lw=0.0))
                    if c:
                        # an ok cell's largest speed: how far it runs from the burst bound
                        text = {"fault": (c["stage"] or "fault").split(" ")[0], "nan": "NaN",
                                "burst": f"{c['max_speed_m_s']:.1f} m/s",
                                "ok": f"{c['max_speed_m_s']:.2f} m/s" + (f"\n{retaken} retaken" if retaken else "")
                                }[c["status"]]
                        ax.text(b + 0.5, a + 0.64, text, ha="center", va="center", fontsize=6.5,
                                linespacing=1.1)
                        ax.text(b + 0.5, a + 0.22, f"{c['wall_s']:.0f} s", ha="center", va="center", fontsize=5.5,
                                color="0.25")
            ax.set_xlim(0, len(subs))
            ax.set_ylim(0, len(segs))
            ax.set_xticks(np.arange(len(subs)) + 0.5, [str(n) for n in subs])
            ax.set_yticks(np.arange(len(segs)) + 0.5, [str(s) for s in segs])
            ax.set_title(f"EI {ei:g} N m², links + contacts {'on' if inter else 'off'}", fontsize=8)
            if i == 1:
                ax.set_xlabel("substeps per frame")
            if j == 0:
                ax.set_ylabel("segments")
    fig.legend(handles=[Patch(color=v, label=k) for k, v in _STATUS_COLOR.items()], loc="lower center", ncol=4,
               fontsize=8, frameon=False)
    fig.suptitle(f"Stability grid: {sweep['scene']} on its head motion, {sweep['duration_s']:g} s per cell\n"
                 f"(ok: its fastest vertex; fault: its stage; burst: a vertex > {sweep['burst_m_s']:g} m/s; hatched: "
                 f"frames taken again in finer steps after a fault or a whip; small: wall time)", fontsize=9)
    fig.tight_layout(rect=(0, 0.05, 1, 0.95))
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


# ---------------------------------------------------------------------------------------------
# suite


def suite_robustness(config, out, log=lambda m: None) -> dict:
    """The ``robustness`` suite of ``hairwarp bench``; ``config.quick`` picks the thin sizes."""
    size = SIZES["quick" if config.quick else "full"]
    res = {"sizes": {k: list(v) if isinstance(v, tuple) else v for k, v in size.items()}}
    timings = {}

    def part(name, fn):
        t0 = time.perf_counter()
        log(f"robustness: {name}")
        res[name] = fn()
        timings[name] = round(time.perf_counter() - t0, 1)

    part("rest", lambda: bench_rest(size["rest_scenes"], size["rest_s"], size["rest_second"], log))
    part("sweep", lambda: bench_sweep(size["sweep_segments"], size["sweep_substeps"], size["sweep_ei"],
                                      size["sweep_s"], log=log))
    part("convergence", lambda: bench_convergence(size["conv_substeps"], size["conv_ref"], size["conv_s"],
                                                  size["conv_overrides"], finer=size["conv_finer"], log=log))
    part("frame_rate", lambda: bench_frame_rate(size["fr_scenes"], size["fr_frames"], log))
    part("teleport", lambda: bench_teleport(size["teleport_after_s"], size["teleport_overrides"], log=log))
    part("extreme", lambda: {"duration_s": size["extreme_s"], "overrides": list(size["extreme_overrides"]),
                             "scenes": [bench_extreme(size["extreme_s"], size["extreme_overrides"], name, log)
                                        for name in size["extreme_scenes"]]})
    part("peers", lambda: bench_peers(size["peer_s"], size["rest_second"], config.peer_timeout_s))
    res["part_wall_s"] = timings
    out = Path(out)
    files = [chart_rest(res["rest"], res["peers"], out / CHART_REST), chart_grid(res["sweep"], out / CHART_GRID)]
    res["files"] = [str(f) for f in files]
    return res


# ---------------------------------------------------------------------------------------------
# report


def _f(x, digits: int = 3) -> str:
    if x is None:
        return "–"
    return f"{x:.{digits}g}"


def _ratio_cell(row: dict) -> str:
    """The rest table's ratio: one pair's, or with redraws their range and the ratio of the means judged."""
    d = row.get("redraws")
    if row.get("still"):
        return f"{_f(row['ratio'])}, still (under {REST_STILL_MM_S:g} mm/s) {_v(row['meets_ratio'])}"
    if not d:
        return f"{_f(row['ratio'])} {_v(row['meets_ratio'])}"
    got = [x for x in d["ratios"] if x is not None]
    spread = f"{_f(min(got))}-{_f(max(got))}" if got else "n/a"
    return (f"{_f(row['ratio'])}; {len(d['ratios'])} draws {spread}, of the means {_f(d['ratio_of_means'])} "
            f"{_v(row['meets_ratio'])}")


def _sticky(run: dict | None) -> str:
    if not run:
        return "–"
    if run["fault"] or run["nan"]:
        return _fault(run)
    return f"{_f(run['second_mm_s'])}, {_f(run['ratio'])}, {_f(run['resting']['max_mm'])}"


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


def _fault(r: dict) -> str:
    if r.get("fault"):
        return f"fault at frame {r['fault']['frame']} in {r['fault']['stage']}"
    return "NaN" if r.get("nan") else "no fault"


def _by_step(r: dict, before: str = "; ", after: str = "") -> str:
    """The links broken by the step alone (``bench_frame_rate``), where the run records them."""
    n = r.get("step_broken_links")
    return "" if n is None else f"{before}{n}{after}"


def _again(r: dict) -> str:
    """The frames taken again at ``links.break_step`` (``bench_frame_rate``), where the run records them."""
    n, m = r.get("refined_frames"), r.get("retaken_frames")
    return (("" if not n else f"; {n} frames taken again")
            + ("" if not m else f"; {m} taken again after a fault or a whip"))


def _retaken_line(sweep: dict) -> str:
    """The grid's line on the cells whose frames were taken again after a fault or a whip (``sim.fault_retries``,
    ``sim.whip_ratio``), or ""."""
    retaken = [c for c in sweep["cells"] if c.get("retaken")]
    if not retaken:
        return ""
    return ("- Frames taken again after a fault or a whip, in twice the steps (`sim.fault_retries`, 2 by default; "
            "`sim.whip_ratio`; the cell is ok when every frame ran): " + "; ".join(
                f"{_cell_name(c)}: {c['retaken']} of {c['frames_done']} (frames "
                + ", ".join(f"{f} in {n}" for f, n, _ in c["retakes"][:4])
                + (", ..." if len(c["retakes"]) > 4 else "") + f"; {c['retakes'][0][2]})" for c in retaken) + ".")


def _cell_name(c: dict) -> str:
    return f"{'on' if c['links_contacts'] else 'off'} EI {c['bend_stiffness']:g} {c['segments']}×{c['substeps']}"


def _v(ok) -> str:
    return "" if ok is None else "✓" if ok else "✗"


def _frame_rate_rest_cell(at: dict | None) -> str:
    """A frame-rate rest run's cell: its second and moving tips, its fault, or – where the report has none."""
    if at is None:
        return "–"
    return _fault(at) if at["fault"] or at["nan"] else f"{_f(at['second_mm_s'])}, {_pct(at['moving_tips_fraction'])}"


def md_robustness(data: dict) -> list[str]:
    """The report section of :func:`suite_robustness`."""
    rest, sweep, conv, fr, tp, peers = (data[k] for k in ("rest", "sweep", "convergence", "frame_rate", "teleport",
                                                          "peers"))
    sm = data.get("machine", {})
    s = rest["second"]
    frame_rate_substeps = rest.get("frame_rate_substeps", REST_FRAME_RATE_SUBSTEPS)
    one_step_substeps = rest.get("one_step_substeps", REST_ONE_STEP_SUBSTEPS)
    lines = ["## Robustness: hair that holds up (`hairwarp bench robustness`)", "",
             "Shipped scenes read as TOML, changed there, run through `Simulation` (public API only); guide points "
             "at 30 fps, no dense hair. ✓ meets the goal, ✗ does not.", "",
             "### Rest", "",
             f"Head held still (`head.motion = {{kind = \"still\"}}`), {rest['duration_s']:g} s, with the scene's "
             f"colliders and without them (`head.shape = \"none\"`, no `[[colliders]]`). Tip speed: finite "
             f"differences of the guide tips between frames, RMS over tips and the frames of second {s}. "
             f"*Moving tips*: tips moving > {rest['moving_mm']:g} mm between the last two frames (goal 0 %: at "
             f"{GOAL_REST_MM_S:g} mm/s a tip moves {GOAL_REST_MM_S / 30:.2f} mm a frame). *Resting vertices*: "
             f"vertices (roots excluded) within a collider's contact layer (+ {1e3 * rest['resting_slack_m']:g} mm) "
             f"in every frame of the last second; their largest motion between frames. *Friction "
             f"{STICKY_FRICTION:g}*: the same run with every collider's friction at {STICKY_FRICTION:g} (mu = "
             f"{STICKY_FRICTION / (1 - STICKY_FRICTION):g}; the scenes ship 0.3, mu = 0.43): what is left of the "
             "motion once the hair can hardly slide over the colliders (second, ratio to no colliders, resting "
             "vertices' largest motion). *Redraws*: a scene whose ratio misses the goal runs three more pairs with "
             f"gravity changed by {', '.join(f'{k:+g}' for k in REST_REDRAWS)} x {PERTURBATION:g} (relative): hair "
             "leaning on hair settles into one of several nearby states, which moves the speed in that second by tens "
             "of per cent with and without colliders alike; the goal is checked on the ratio of the four pairs' means. "
             f"*Still*: tips under {REST_STILL_MM_S:g} mm/s with the colliders meet the ratio whatever it is: both "
             "runs are then still, and their ratio is one of float32 round-off. "
             f"*At {frame_rate_substeps} and {one_step_substeps} substeps* (no goal: the goals are at the shipped "
             "steps): the same still head at frame-rate steps, where the links and hair contacts are solved after "
             "the free step (second, moving tips).",
             "",
             f"![rest]({CHART_REST})", "",
             f"| scene | second {s} [mm/s] (goal ≤ {GOAL_REST_MM_S:g}) | without colliders [mm/s] | ratio (goal ≤ "
             f"{GOAL_REST_RATIO:g}×) | tips per second 1..{int(rest['duration_s'])} [mm/s] | moving tips (goal 0 %) "
             f"| resting vertices: count, max per frame [mm] (goal < {GOAL_RESTING_MM:g}) "
             f"| friction {STICKY_FRICTION:g}: second {s} [mm/s], ratio, resting max [mm] "
             f"| at {frame_rate_substeps} substeps: second {s} [mm/s], moving tips "
             f"| at {one_step_substeps} substep: second {s} [mm/s], moving tips |",
             "|---|---:|---:|---:|---|---:|---|---|---|---|"]
    for row in rest["rows"]:
        if row.get("status") != "ok":
            lines.append(f"| `{row['scene']}` | skipped: {row.get('message')} | | | | | | | | |")
            continue
        fr_cell, one_cell = (_frame_rate_rest_cell(row.get(k)) for k in ("frame_rate", "one_step"))
        c, n, rv = row["colliders"], row["no_colliders"], row["resting"]
        faults = "".join(f" ({k.replace('_', ' ')}: {_fault(row[k])})" for k in ("colliders", "no_colliders")
                         if row[k]["fault"] or row[k]["nan"])
        lines.append(f"| `{row['scene']}`{faults} | {_f(c['second_mm_s'])} {_v(row['meets_speed'])} "
                     f"| {_f(n['second_mm_s'])} | {_ratio_cell(row)} "
                     f"| {', '.join(_f(x, 2) for x in c['rms_speed_per_second_mm_s'])} "
                     f"| {_pct(c['moving_tips_fraction'])} {_v(c['moving_tips_fraction'] == 0)} "
                     f"| {rv['vertices']}, {_f(rv['max_mm'])} {_v(row['meets_resting'])} "
                     f"| {_sticky(row.get('sticky'))} | {fr_cell} | {one_cell} |")
    ok_rows = [row for row in rest["rows"] if row.get("status") == "ok" and row.get("sticky")
               and not (row["sticky"]["fault"] or row["sticky"]["nan"])]
    slid = [row["scene"] for row in ok_rows if (not row["meets_ratio"] or not row["meets_resting"])
            and (row["sticky"]["ratio"] or 0.0) <= GOAL_REST_RATIO
            and (row["sticky"]["resting"]["max_mm"] or 0.0) < GOAL_RESTING_MM]
    if slid:
        lines += ["", f"- At friction {STICKY_FRICTION:g} {', '.join(f'`{x}`' for x in slid)} "
                      f"{'meets' if len(slid) == 1 else 'meet'} the ratio and resting-vertex goals "
                      f"{'it misses' if len(slid) == 1 else 'they miss'} as shipped: the motion left there is hair "
                      "sliding over the colliders at its friction cone's edge, as Coulomb's law lets it."]
    worse = [row for row in ok_rows if (row["sticky"]["second_mm_s"] or 0.0) > (row["colliders"]["second_mm_s"] or 0.0)
             * 1.5]
    if worse:
        lines += ["", f"- Faster at friction {STICKY_FRICTION:g} than as shipped in second {s}: " + ", ".join(
            f"`{row['scene']}` ({_f(row['sticky']['second_mm_s'])} against {_f(row['colliders']['second_mm_s'])} "
            "mm/s)" for row in worse) + "."]
    free = [row["scene"] for row in rest["rows"] if row.get("status") == "ok"
            and (row["no_colliders"]["second_mm_s"] or 0.0) > GOAL_REST_MM_S]
    if free:
        lines += ["", f"- Above the goal in second {s} without colliders too: {', '.join(f'`{x}`' for x in free)} "
                      "(they have not settled even with nothing to touch: the ratio is the fairer reading there)."]
    lines += ["", "### Stability grid", "",
              f"`{sweep['scene']}` on its shipped head motion for {sweep['duration_s']:g} s per cell, segments × "
              f"substeps × links and contacts on/off × EI. *fault*: `SimulationFault` (its stage), *NaN*: non-finite "
              f"guide points without a fault, *burst*: a vertex faster than {sweep['burst_m_s']:g} m/s "
              f"(`guide_curves()` velocities, every frame) without a fault. Goal: every cell ok.", "",
              f"![grid]({CHART_GRID})", "",
              f"- **{sweep['counts']['ok']} of {len(sweep['cells'])} cells ok** {_v(sweep['meets'])}; "
              f"{sweep['counts']['fault']} faults, {sweep['counts']['nan']} NaN, {sweep['counts']['burst']} bursts"
              + (f"; {sweep['near']} near the limit, {sweep['near_not_ok']} of them not ok when run again"
                 if sweep.get("near") else "")
              + f"; {sweep['wall_s']:.0f} s for the grid (largest cell "
              f"{max(c['wall_s'] for c in sweep['cells']):.0f} s)."]
    retaken = _retaken_line(sweep)
    if retaken:
        lines.append(retaken)
    bad = [c for c in sweep["cells"] if c["status"] != "ok"]
    if bad:
        lines.append("- Not ok: " + "; ".join(
            f"{_cell_name(c)}: " + (f"{c['stage']} frame {c['fault_frame']}" if c["status"] == "fault" else
                                    f"{c['status']} {c['max_speed_m_s']:.2g} m/s") for c in bad) + ".")
    near = [c for c in sweep["cells"] if "reruns" in c]
    if near:
        changes = ", ".join(f"{r['gravity_change']:+.0e}" for r in near[0]["reruns"])
        lines.append(f"- Cells whose fastest vertex came within {100 * sweep['near_fraction']:.0f} % of the burst "
                     f"speed, run again with gravity changed by {changes}"
                     + " (relative; a whip near the limit crosses it in some runs and not in others, and the goal "
                       "counts them all): " + "; ".join(
                         f"{_cell_name(c)}: {c['max_speed_m_s']:.2f} m/s, again "
                         + ", ".join(f"{r['max_speed_m_s']:.2f}" + ("" if r["status"] == "ok" else f" ({r['status']})")
                                     for r in c["reruns"]) for c in near) + ".")
    ref_n = conv["reference_substeps"]
    lines += ["", "### Convergence in the substeps", "",
              f"`{conv['scene']}`{' (' + ', '.join(conv['overrides']) + ')' if conv['overrides'] else ''}, "
              f"{conv['duration_s']:g} s on its head motion: tips against the {conv['reference_substeps']}-substep "
              f"run, RMS over frames and guides; *no links*: `links.enabled = false` (contacts as shipped). Goal "
              f"(these two): the difference falls at least linearly in the step: the order fitted over every run, "
              f"the order of the finest halving (16 → 8 substeps' difference) and that of the differences between "
              f"successive runs (below) all ≥ {conv['goal_order']:g}. "
              f"Without a goal, where an order is lost: *free hair* (no links, hair contacts or colliders: the "
              f"integrator's own order) and *colliders only* (no links or hair contacts). *Orders*: "
              f"of each halving, coarse to fine. The runs of 7 substeps and fewer (steps of 1/220 s or longer) "
              f"solve the links and contacts after the free step (`response = \"auto\"`) and give their body "
              f"contacts the share law of friction (a new contact sticks; docs/collision.md), the finer ones as "
              f"shipped, with friction continuous in the state: a fitted order across the two forms says less than "
              f"the finest halving, and a coarse run more accurate than first order from the finer ones predicts "
              f"lowers it (when the links' sweeps came to run at one step a frame too, on 2026-12-04, the links' "
              f"1-substep row fell from 11.7 to 5.25 mm and their fitted order from 0.97 to 0.74). *{ref_n} again*: "
              f"the "
              f"reference run once more with gravity changed by {conv.get('perturbation', PERTURBATION):g} "
              f"(relative), its tips against the reference's [mm]: a difference at that floor is the scene's "
              f"sensitivity (strands that slide off the head or each other one way or the other), not the step's "
              f"error, and shows no order. Since the body contacts' friction reaches its cone (2026-12-06, "
              f"docs/collision.md, \"Friction that reaches its cone and converges\") that floor is 7-10 times lower "
              f"(links 0.068 → 0.010 mm, no links 0.98 → 0.097, colliders only 0.066 → 0.024), and the colliders "
              f"alone part at the finest halvings by 0.77 and 0.52 mm where they parted by 1.14 and 0.89.", "",
              f"| variant | {ref_n} again [mm] | " + " | ".join(f"{r['substeps']} substeps [mm]" for r in
                                                           next(iter(conv["variants"].values()))["rows"])
              + " | fitted order | orders of each halving | strands > 50 mm at the end |",
              "|---|---:|" + "---:|" * (len(next(iter(conv["variants"].values()))["rows"]) + 3)]
    for label, v in conv["variants"].items():
        cells = [(_f(r["tip_rms_mm"]) if r["fault"] is None else f"fault fr. {r['fault']['frame']}")
                 for r in v["rows"]]
        ref = f" (reference: {_fault({'fault': v['reference_fault']})})" if v["reference_fault"] else ""
        lines.append(f"| {label}{ref} | {_f(v.get('reference_again_mm'))} | " + " | ".join(cells)
                     + f" | {_f(v['order'], 2)} "
                     f"| {', '.join(_f(x, 2) for x in v.get('local_orders', []))} {_v(v['meets'])} | "
                     + ", ".join(str(r["strands_over_50mm_at_end"]) for r in v["rows"]) + " |")
    spread = [(label, v) for label, v in conv["variants"].items()
              if all(r.get("median_strand_mm") is not None for r in v["rows"])]
    if spread:
        lines += ["", f"The same differences strand by strand: the median strand's RMS over frames, and the share of "
                  f"the mean square that the {WORST_STRANDS} strands farthest from the reference carry (of "
                  f"{conv.get('strands', 'all')}).", "",
                  "| variant | median strand [mm], " + ", ".join(str(r["substeps"]) for r in spread[0][1]["rows"])
                  + " substeps | fitted order | worst strands' share |", "|---|---|---:|---|"]
        for label, v in spread:
            medians = ", ".join(_f(r["median_strand_mm"]) for r in v["rows"])
            shares = ", ".join(_pct(r["worst_share"]) for r in v["rows"])
            lines.append(f"| {label} | {medians} | {_f(v.get('median_order'), 2)} | {shares} |")
    with_successive = [(label, v) for label, v in conv["variants"].items() if v.get("successive")]
    if with_successive:
        pairs = ", ".join(f"{d['substeps'][0]}-{d['substeps'][1]}" for d in with_successive[0][1]["successive"])
        changes = ", ".join(f"{c['gravity_change']:g}" for c in with_successive[0][1]["sensitivity"])
        lines += ["", f"Each run against the next finer, to {conv['finer'][-1] if conv.get('finer') else ref_n} "
                  f"substeps, RMS over frames and guides, and the order of each halving: a method of order p "
                  f"divides these differences by 2^p at every halving, where the differences to one reference above "
                  f"divide by 2^p + 1 at the halving next to it (the finest halving's 1.58 in a first-order method). "
                  f"*Gravity changed*: the {ref_n}-substep run with gravity changed by {changes} (relative), its tips "
                  f"against the reference's, and the exponent of that answer in the change. The step's error is "
                  f"such a change, and a scene that answers a change of gravity less than in proportion (an exponent "
                  f"below 1: strands that settle on one side of the head or of each other, or on the other) answers "
                  f"the step's error alike: its differences fall more slowly than the error does. Where the answer is "
                  f"in proportion (free hair), the orders are the integrator's own: backward Euler's damping of the "
                  f"strands' bending modes, which these steps pass through (`hairwarp.Integrator`): taken at the "
                  f"step's end, a joint's spring damps it by h K besides the hair's own damping C, more than it until "
                  f"the step falls below C / K (1 ms for `long_hair`'s hair, 32 substeps), and the orders come near 1 "
                  f"only past it.", "",
                  f"| variant | {pairs} substeps [mm] | orders | median strand's orders | gravity changed [mm] | "
                  f"exponent |", "|---|---|---|---|---|---:|"]
        for label, v in with_successive:
            lines.append(f"| {label} | {', '.join(_f(d['tip_rms_mm']) for d in v['successive'])} "
                         f"| {', '.join(_f(x, 2) for x in v['successive_orders'])} "
                         f"| {', '.join(_f(x, 2) for x in v['successive_median_orders'])} "
                         f"| {', '.join(_f(c['tip_rms_mm']) for c in v['sensitivity'])} "
                         f"| {_f(v.get('sensitivity_order'), 2)} |")
    lines += ["", "### Frame-rate steps", "",
              f"Each shipped scene with links (the scene's `[links]`; the defaults where it ships none, marked *), its "
              f"head motion and frames, at 2 and 1 substeps against {fr['reference_substeps']}: tips RMS over frames "
              f"and guides. Goals: 2 substeps no fault, no broken link, ≤ {fr['goal_2_mm']:g} mm; 1 substep (one "
              f"step a frame) no fault, ≤ {fr['goal_1_mm']:g} mm. At 7 substeps and fewer (steps of 1/220 s or "
              "longer) the links' and hair contacts' forces are solved after the free step, on each pair's relative "
              "motion (`response = \"auto\"`, docs/interactions.md), then both again by Gauss-Seidel sweeps between "
              "strands (`links.sweeps` per 1/240 s of step that starts from the links' last force, a step k times "
              "as long k^2 times as many, one that starts cold twice as many, k^1.5 times those: 16 at 2 substeps, "
              "25 at 1, the count of 1/45 s). *4 substeps*: between frame "
              "rate and the shipped 8, no goal (broken links, tips [mm]); a hole between the forms `auto` hands over "
              "between would show here. *16 again*: the reference run once more with gravity changed by "
              f"{fr.get('perturbation', PERTURBATION):g} (relative): broken links, tips against the reference [mm], "
              "how closely any run can follow the reference's motion (since the body contacts' friction reaches its "
              "cone, 2026-12-06, one strand of `long_hair_shoulders`' 120 lands on the other side of the shoulder: "
              "76.6 mm of its 7.0 mm RMS, the median strand 0.01 mm). *Broken links*: at the step (at 16 substeps; "
              "by the step: those neither reference run breaks, which break with the step, not the motion; frames "
              "taken again: a frame of steps longer than `links.break_step`, 1/120 s, in which a link broke is taken "
              "again from its start in steps that short, and its breaks are that frame's; taken again after a fault "
              "or a whip: a frame that faults, or whose guides end it past `sim.whip_ratio` (2) times the speed the "
              "motion explains, is taken again from its start in twice the steps, up to `sim.fault_retries` (2) "
              "times).", "",
              "| scene | 16 again | 4 substeps | 2 substeps | broken links (at 16; by the step) | tips [mm] | verdict "
              "| 1 substep | broken links (by the step) | tips [mm] | verdict |",
              "|---|---|---|---|---:|---:|---|---|---:|---:|---|"]
    for row in fr["rows"]:
        if row.get("status") != "ok":
            lines.append(f"| `{row['scene']}` | skipped: {row.get('message')} | | | | | | | | | |")
            continue
        two, one = row["2"], row["1"]
        mark = "" if row["links_shipped"] else " *"
        four = row.get("4")
        mid = "–" if four is None else (f"{four['broken_links']} broken, {_f(four['tip_rms_mm'])}"
                                        if four["fault"] is None else _fault(four))
        again = row.get("reference_again")
        spread = "–" if again is None else (f"{again['broken_links']} broken, {_f(again['tip_rms_mm'])}"
                                            if again["fault"] is None else _fault(again))
        lines.append(f"| `{row['scene']}`{mark} | {spread} | {mid} | {_fault(two)} | {two['broken_links']} "
                     f"({two['reference_broken_links']}{_by_step(two)}{_again(two)}) | {_f(two['tip_rms_mm'])} | "
                     f"{_v(two['meets'])} | {_fault(one)} | {one['broken_links']}"
                     f"{_by_step(one, ' (', _again(one) + ')')} | {_f(one['tip_rms_mm'])} | {_v(one['meets'])} |")
    lines += ["", "### Head teleport", "",
              f"`{tp['scene']}`{' (' + ', '.join(tp['overrides']) + ')' if tp['overrides'] else ''} with links and "
              f"contacts; the head still, then keyframes move it {TELEPORT_M:g} m along x from "
              f"t = {tp['jump_at_s']:g} s, within 1 ms (a teleport) or within 2 frames. {tp['after_s']:g} s after "
              f"the move: RMS speed of the tips relative to the head (positions in the head frame, between frames). "
              f"Goal: no fault, ≤ {tp['goal_m_s']:g} m/s.", ""]
    if not tp["teleport_distance_available"]:
        lines += ["`head.teleport_distance` is not in this checkout's scene schema: reported as not available; "
                  "the runs below are without it.", ""]
    lines += ["| case | `head.teleport_distance` | outcome | tips relative to the head 1 s after [m/s] | verdict |",
              "|---|---|---|---:|---|"]
    for r in tp["rows"]:
        td = "unset" if r["teleport_distance"] is None else f"{r['teleport_distance']:g} m"
        lines.append(f"| {r['case']} | {td} | {_fault(r)} | {_f(r['relative_tip_rms_m_s'])} | {_v(r['meets'])} |")
    ex = data.get("extreme")
    if ex:
        runs = ex["scenes"] if "scenes" in ex else [ex]  # one scene's dict in reports before the scenes were listed
        names = ", ".join(f"`{r['scene']}`" for r in runs)
        lines += ["", "### Extreme motion", "",
                  f"{names}{' (' + ', '.join(ex['overrides']) + ')' if ex['overrides'] else ''}, each at its "
                  f"substeps for {ex['duration_s']:g} s on a head spinning at {SPIN_REV_S:g} rev/s (keyframes every "
                  f"20°) and on its own motion {TURN_FACTOR:g}x faster; as shipped (links, contacts, colliders) "
                  "and as free hair (none of them). `long_hair` solves its links in the free step, "
                  "`long_hair_shoulders` by sweeps after it, `fast_turn` its links and hair contacts by sweeps. "
                  "*Taken again*: frames taken again in finer steps, after a fault or because their guides ended "
                  "them past `sim.whip_ratio` times the speed the motion explains (README, Faults). *At "
                  f"{EXTREME_REFERENCE_SUBSTEPS} substeps*: the run as shipped once more at that step, its largest "
                  "speed and broken links. Goal: no fault, no NaN.", "",
                  f"| scene | motion | hair | outcome | taken again | largest speed [m/s] | broken links | at "
                  f"{EXTREME_REFERENCE_SUBSTEPS} substeps: speed, links | verdict |",
                  "|---|---|---|---|---|---:|---:|---|---|"]
        for run in runs:
            for r in run["rows"]:
                broken = r["broken_links"] if r["broken_links"] is not None else "–"
                again = ", ".join(f"{f} in {n} ({stage})" for f, n, stage in r.get("retakes", [])) or "–"
                ref = r.get("fine")
                fine = ("–" if ref is None else f"{_f(ref['max_speed_m_s'])}, {ref['broken_links']}"
                        if ref["fault"] is None else f"fault at frame {ref['fault']['frame']}")
                lines.append(f"| {run['scene']} | {r['case']} | {'free' if r['free'] else 'as shipped'} | "
                             f"{_fault(r)} | {again} | {_f(r['max_speed_m_s'])} | {broken} | {fine} | "
                             f"{_v(r['meets'])} |")
    lines += ["", "### Peers", ""]
    mj = peers["mujoco_rest"]
    nw = peers.get("newton_rest") or {"status": "not run"}
    setup = []
    if mj.get("status") == "ok":
        setup.append(f"MuJoCo {mj['mujoco']}: the chain of `peers.py` ({mj['segments']} segments of 0.3 m, EI "
                     f"{mj['bend_stiffness']:g} N m² as joint springs, capsule geoms of the strand's radius, "
                     f"`{mj['integrator']}` at {mj['dt'] * 1e3:.3g} ms), released from the 80° tilt onto a static "
                     f"capsule (radius {PEER_CAPSULE['radius']:g} m) or onto a floor, {mj['duration_s']:g} s; the "
                     f"same without contacts. Tip speed from 30 fps samples as above; *resting*: joint points within "
                     f"the strand's radius + 1 mm of the collider over the last second.")
    if nw.get("status") == "ok":
        clear = ", ".join(f"{c} {_f(e['contact']['min_clearance_mm'], 2)} mm" for c, e in nw["results"].items())
        setup.append(f"Newton {nw['newton']}: the same strand as a VBD rod (`add_rod`, {nw['segments']} capsule "
                     f"bodies with the cylinder mass properties, EI / L as bend and twist stiffness and the hair "
                     f"damping at every rod joint, the root a rod joint to the world with the same spring), "
                     f"`{nw['solver']}` with {nw['iterations']} iterations at {nw['dt'] * 1e3:.3g} ms, shape contacts "
                     f"from `CollisionPipeline` (stiffness {nw['contact_stiffness']:g} N/m, friction 0.5) on a static "
                     f"capsule shape or ground plane placed as MuJoCo's, {nw['duration_s']:g} s; smallest clearance "
                     f"between rod and collider over the run (negative: inside): {clear}. At "
                     f"{nw['iterations']} iterations the rod's bending springs barely act (without them its motion "
                     f"is nearly the same, as is MuJoCo's chain without its springs), so it wraps the capsule where "
                     f"the chain lies across it: the rows compare the solvers as they run, not one motion.")
    if setup:
        lines.append(" ".join(setup))
    runs = [(name, r) for name, r in (("MuJoCo", mj), ("Newton", nw)) if r.get("status") == "ok"]
    if runs:
        lines += ["", f"| peer, collider | second {peers['second']} [mm/s] (goal ≤ {GOAL_REST_MM_S:g}) | without "
                  f"contacts | ratio (goal ≤ {GOAL_REST_RATIO:g}×) | resting points, max per frame [mm] (goal < "
                  f"{GOAL_RESTING_MM:g}) |", "|---|---:|---:|---:|---|"]
        for name, r in runs:
            for collider, e in r["results"].items():
                rv = e["contact"].get("resting", {})
                lines.append(f"| {name}, {collider} | {_f(e['second_mm_s'])} "
                             f"{_v(e['second_mm_s'] is not None and e['second_mm_s'] <= GOAL_REST_MM_S)} "
                             f"| {_f(e['no_contact_second_mm_s'])} | {_f(e['ratio'])} "
                             f"{_v(e['ratio'] is not None and e['ratio'] <= GOAL_REST_RATIO)} "
                             f"| {rv.get('points')}, {_f(rv.get('max_mm'))} "
                             f"{_v(rv.get('max_mm') is not None and rv['max_mm'] < GOAL_RESTING_MM)} |")
        lines += ["", "A strand without contacts has no air drag and only the hair damping in its joints: it swings "
                  "on, so its ratio says little; the figures with contacts are the comparison."]
    failed = [f"- {name} at rest: {r.get('status')}: {r.get('message', '')[:200]}"
              for name, r in (("MuJoCo", mj), ("Newton", nw)) if r.get("status") != "ok"]
    lines += ([""] if runs and failed else []) + failed
    lines += [""] + [f"- {k}: {v}." for k, v in peers["not_modelled"].items()]
    pw = data.get("part_wall_s", {})
    lines += ["", f"*Suite `robustness`: {data.get('wall_s')} s (" + ", ".join(f"{k} {v} s" for k, v in pw.items())
              + f") on {sm.get('date')}{machine_words(sm)}, load average {sm.get('load_average_start')} → "
              f"{sm.get('load_average_end')}"
              + ("; quick sizes" if data.get("quick") else "") + "."
              + _rerun_note(data.get("rerun")) + "*"]
    return lines


def _rerun_note(rerun: dict | None) -> str:
    """The parts of a record run again on their own later and merged into it (``{"date", "git_commit", "parts"}``)."""
    if not rerun:
        return ""
    return f" Rerun on {rerun['date']} at commit {rerun['git_commit']}: {', '.join(rerun['parts'])}."


def summary_md(data: dict) -> str:
    """One line for the report's summary: each part's goal met or not, and the scenes or variants that miss it."""
    def part(name, rows, met, label):
        missed = [label(r) for r in rows if not met(r)]
        verdict = "✓" if not missed else f"✗ ({', '.join(missed)})"
        return f"{name} {len(rows) - len(missed)} of {len(rows)} {verdict}"

    rest = [r for r in data["rest"]["rows"] if r.get("status") == "ok"]
    frame_rate = [r for r in data["frame_rate"]["rows"] if r.get("status") == "ok"]
    extreme = [(run["scene"], r) for run in data["extreme"].get("scenes", [data["extreme"]]) for r in run["rows"]]
    conv = [(label, v) for label, v in data["convergence"]["variants"].items() if v["meets"] is not None]
    sweep = data["sweep"]
    parts = [
        part("at rest with the head still", rest, lambda r: r["meets_speed"] and r["meets_ratio"]
             and r["meets_resting"], lambda r: r["scene"]),
        f"stability grid {sweep['counts']['ok']} of {len(sweep['cells'])} cells {'✓' if sweep['meets'] else '✗'}",
        part("frame-rate steps", frame_rate, lambda r: r["2"]["meets"] and r["1"]["meets"], lambda r: r["scene"]),
        part("teleports", data["teleport"]["rows"], lambda r: r["meets"], lambda r: r["case"]),
        part("extreme motions", extreme, lambda e: e[1]["meets"], lambda e: f"{e[0]} {e[1]['case']}"),
        part("convergence in the step", conv, lambda c: c[1]["meets"],
             lambda c: f"{c[0]}, order {_f(c[1]['order'], 2)}"),
    ]
    return "- Robustness (goals of section \"Robustness\"): " + "; ".join(parts) + "."


def summary(data: dict) -> list[str]:
    """Plain-text lines for the terminal."""
    out = []
    for row in data["rest"]["rows"]:
        if row.get("status") == "ok":
            out.append(f"rest {row['scene']}: {_f(row['colliders']['second_mm_s'])} mm/s in second "
                       f"{data['rest']['second']} (goal <= {GOAL_REST_MM_S:g}) {_v(row['meets_speed'])}, ratio "
                       f"(goal <= {GOAL_REST_RATIO:g}) {_ratio_cell(row)}")
    sw = data["sweep"]
    out.append(f"sweep: {sw['counts']['ok']}/{len(sw['cells'])} cells ok {_v(sw['meets'])}")
    for label, v in data["convergence"]["variants"].items():
        goal = "no goal" if v["meets"] is None else f"goal >= {GOAL_ORDER:g}"
        out.append(f"convergence {label}: order {_f(v['order'], 2)}, finest halving {_f(v.get('finest_order'), 2)}, "
                   f"between successive runs {_f((v.get('successive_orders') or [None])[-1], 2)} ({goal}) "
                   f"{_v(v['meets'])}; the reference again {_f(v.get('reference_again_mm'))} mm, the scene's answer "
                   f"to gravity's change of exponent {_f(v.get('sensitivity_order'), 2)}")
    return out
