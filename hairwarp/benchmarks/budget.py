"""Suite ``budget`` of ``hairwarp bench``: model no more than a scene needs.

For each shipped scene a REFERENCE run at the most faithful settings (more segments and substeps than the
scene ships, its colliders and interactions as designed) is compared with variants that change ONE
modelling choice at a time: ``sim.segments``, ``sim.substeps``, the head collider (the analytic ellipsoid
against triangle meshes of it and the analytic sphere), a capsule as a mesh, static links and contacts off, and the
dense strand count. Each variant gets

- a cost: CPU seconds per simulated frame, the median of its frame times after ``WARMUP_FRAMES`` (kernel
  loading excluded; the dense hair is not in it), timed as the CPU time of the thread that runs Warp's CPU
  kernels, so other programs on the machine's cores do not add to it (on CUDA: wall time to a sync); or for
  ``dense.count`` the seconds per output frame of the dense hair (interpolation, push-out, Hermite samples
  or Catmull-Rom vertices as the scene writes them, and the copy to the host);
- a tip error: RMS over frames and guides of the guide tips' distance to the reference's [m]
  (:func:`tip_rms_error`; every segment count has tips, so any two runs of one groom compare);
- a look: the silhouette of the dense hair from the preview's ``three_quarter`` camera, rasterised into
  ``PIXEL_M`` pixels, against the reference's, as the intersection over union of the coverage masks
  (:func:`coverage_mask`, :func:`silhouette_iou`), averaged over ``LOOK_FRAMES`` frames.

A setting is within the bound when its tip error is at most ``TIP_BOUND_M`` and its mean IoU at least
``IOU_BOUND``; the cheapest such setting of each choice is marked, and the COMBINED cheapest settings are
run again against the same reference, since errors of separate choices add (a pick saving less than
``MIN_SAVING`` of the shipped option's cost, or a mesh file written here, keeps the shipped option there).
The reference is also run with gravity 1e-5 stronger (``FLOOR_GRAVITY``): how far that moves the tips is the
run's own sensitivity, a floor under every error. A run that leaves the solver's bounds
(``SimulationFault``) is recorded as unstable, with its frame and message.
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# A guide tip within 1 cm of the reference's stays among its own wisp's dense strands: guides are about 1 cm
# apart on the generated scalps, the dense hair between them is interpolated, and its tips scatter by
# dense.tip_spread = 5 mm besides. A tighter bound would judge the reference's own spread: equally faithful
# settings (the head as a 1280- or a 5120-triangle ellipsoid mesh; 20 or 24 segments) differed by 5-7 mm.
TIP_BOUND_M = 1.0e-2
# 95 % of the silhouette's pixels shared: a difference of one pixel (4 mm) along an outline of a few
# hundred pixels is some 1-3 % of the area of a head of hair, so 5 % is a visible but small change.
IOU_BOUND = 0.95
PIXEL_M = 4.0e-3  # [m] coverage mask pixel: a wisp's width (the guides' radius is 2 mm)
VIEW = "three_quarter"  # the camera of the scene previews
LOOK_FRAMES = 4  # frames whose silhouettes are compared, evenly spread over the run
LOOK_DENSE_COUNT = 3000  # dense strands of the look when a scene writes none (long_hair's default)
FLOOR_GRAVITY = (0.0, 0.0, -9.81 * (1.0 + 1.0e-5))  # [m/s^2] the reference run again with this gravity
# A setting replaces the shipped one in the combined run only when it saves at least this share of the
# shipped option's cost: medians of separate runs of equal work scatter by up to 25 % on this shared 2-core
# machine (the head as a 320-, 1280- and 5120-triangle mesh timed 78, 106 and 91 ms per frame).
MIN_SAVING = 0.3
WARMUP_FRAMES = 2  # frame times left out of the cost: the first frames load the kernels
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Choice:
    """One modelling choice: the scene's value, and the options tried instead of the reference's."""

    name: str
    key: str  # what the setting is, for the report (e.g. "sim.segments")
    options: list  # [(label, overrides)], the reference's own option included (overrides [])
    shipped: str  # label of the option the scene ships
    dense: bool = False  # evaluated on the reference's frames, no run of its own


@dataclass
class Plan:
    """What the suite does for one scene."""

    name: str
    path: Path
    reference: list  # overrides of the reference run
    duration_s: float  # simulated time of each run [s]
    choices: list
    base: list = field(default_factory=list)  # overrides of every run (cut-down groom)
    notes: list = field(default_factory=list)
    quick: bool = False  # smoke sizes: three look frames, no floor run


# ---------------------------------------------------------------------------------------------
# metrics


def tip_rms_error(tips: np.ndarray, reference: np.ndarray) -> float:
    """RMS over frames and guides of the distance between guide tips and the reference's [m].

    Args:
        tips, reference: (F, G, 3) tip positions of the same frames and guides.
    """
    a, b = np.asarray(tips, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"tip arrays differ in shape: {a.shape} and {b.shape}")
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


@dataclass(frozen=True)
class Grid:
    """A pixel grid on the screen plane of a view: ``origin`` (screen x, y) of pixel (0, 0) [m], ``pixel``
    size [m], ``shape`` (rows, cols); ``right``/``up`` are the screen axes in world."""

    right: np.ndarray
    up: np.ndarray
    origin: tuple
    pixel: float
    shape: tuple

    @classmethod
    def around(cls, points2d: np.ndarray, right, up, pixel: float = PIXEL_M, pad: float = 0.15) -> Grid:
        """A grid covering ``points2d`` (N, 2) screen coordinates, with ``pad`` of the extent added each side."""
        lo, hi = points2d.min(axis=0), points2d.max(axis=0)
        margin = pad * (hi - lo) + 2 * pixel
        lo, hi = lo - margin, hi + margin
        cols, rows = (int(math.ceil(v)) for v in (hi - lo) / pixel)
        return cls(np.asarray(right, float), np.asarray(up, float), (float(lo[0]), float(lo[1])), float(pixel),
                   (rows, cols))


def project(points: np.ndarray, right, up) -> np.ndarray:
    """Orthographic screen coordinates (N, 2) [m] of world points (N, 3)."""
    p = np.asarray(points, dtype=np.float64)
    r, u = np.asarray(right, float), np.asarray(up, float)
    # sums of products, not a matrix product: no BLAS threads left spinning beside the timed frames
    return np.stack([p[:, 0] * r[0] + p[:, 1] * r[1] + p[:, 2] * r[2],
                     p[:, 0] * u[0] + p[:, 1] * u[1] + p[:, 2] * u[2]], axis=1)


def coverage_mask(points: np.ndarray, counts: np.ndarray, grid: Grid) -> np.ndarray:
    """Pixels of ``grid`` crossed by the polylines ``points`` (N, 3) [m] with ``counts`` vertices each.

    Each segment is sampled at most half a pixel apart, so a polyline leaves no gap; samples off the grid
    land on its border pixels. Returns a bool (rows, cols) mask, row 0 at the bottom.
    """
    xy = project(points, grid.right, grid.up)
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    ok = np.ones(len(xy) - 1, dtype=bool) if len(xy) > 1 else np.zeros(0, dtype=bool)
    ok[(starts + counts - 1)[:-1]] = False  # no segment from one curve's last point to the next curve's first
    a, b = xy[:-1][ok], xy[1:][ok]
    mask = np.zeros(grid.shape, dtype=bool)
    if len(a) == 0:
        if len(xy):
            _mark(mask, xy, grid)
        return mask
    n = int(min(64, max(1, math.ceil(np.max(np.linalg.norm(b - a, axis=1)) / (0.5 * grid.pixel)))))
    t = np.linspace(0.0, 1.0, n + 1)
    samples = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
    _mark(mask, samples.reshape(-1, 2), grid)
    return mask


def _mark(mask: np.ndarray, xy: np.ndarray, grid: Grid) -> None:
    rows, cols = grid.shape
    c = np.clip(np.floor((xy[:, 0] - grid.origin[0]) / grid.pixel).astype(np.int64), 0, cols - 1)
    r = np.clip(np.floor((xy[:, 1] - grid.origin[1]) / grid.pixel).astype(np.int64), 0, rows - 1)
    mask[r, c] = True


def silhouette_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two coverage masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def cheapest_within(rows: list, tip_bound: float = TIP_BOUND_M, iou_bound: float = IOU_BOUND) -> str | None:
    """Label of the cheapest row (by ``cost_s``) whose tip error and look are within the bounds, or None.

    A row's ``tip_rms_m`` None means the choice does not move the guides (dense hair); ``iou`` None means no
    look was measured. An unstable row never qualifies.
    """
    best = None
    for r in rows:
        if not within(r, tip_bound, iou_bound) or r.get("cost_s") is None:
            continue
        if best is None or r["cost_s"] < best["cost_s"]:
            best = r
    return None if best is None else best["label"]


def applicable(row: dict) -> bool:
    """The row's setting is a scene value: not a mesh file the suite wrote for the variant."""
    return not any(".file=" in o for o in row.get("overrides", []))


def within(row: dict, tip_bound: float = TIP_BOUND_M, iou_bound: float = IOU_BOUND) -> bool:
    """The row ran to the end with a tip error <= ``tip_bound`` and a mean IoU >= ``iou_bound``."""
    if row.get("status") != "ok":
        return False
    tip, iou = row.get("tip_rms_m"), row.get("iou")
    return (tip is None or tip <= tip_bound) and (iou is None or iou >= iou_bound)


# ---------------------------------------------------------------------------------------------
# runs


def _dense_for(sim, count: int):
    """A DenseHair of ``count`` strands on ``sim``'s model, with the scene's other dense settings."""
    scene = sim.scene.with_overrides([f"dense.count={int(count)}"])
    return sim._build_dense(scene.dense)


def _dense_points(sim, dense, hermite: bool):
    """(points (N, 3), vertex counts per curve) of ``dense`` on ``sim``'s current guides, pushed out like
    ``Simulation.dense_curves`` does."""
    s, c = sim.stepper.state, sim.stepper.control
    colliders = sim.collider_set if sim.scene.dense.push_out else None
    points, _ = dense.evaluate(s.vertex_positions, None, c.head_xform, c.head_velocity, hermite=hermite,
                               colliders=colliders)
    return points.numpy().copy(), dense.curve_vertex_counts(hermite)  # a copy: numpy() views the buffer


def run_scene(scene, frames: int, *, look_frames=(), look_counts=(), grid: Grid | None = None,
              dense_timing: tuple = (), device: str = "cpu") -> dict:
    """Advance ``scene`` ``frames`` frames; record frame times, tips and the dense hair's looks.

    Args:
        scene: a :class:`hairwarp.Scene`.
        frames: frames to simulate after frame 0.
        look_frames: frames whose dense hair is rendered into masks.
        look_counts: dense strand counts rendered at each look frame.
        grid: the pixel grid; None keeps the screen points instead (the reference's, to place a grid).
        dense_timing: dense counts whose output cost is timed at the look frames (the scene's basis).

    Returns:
        ``{"status" ("ok" | "unstable" | "error"), "message", "frame_s" (list), "tips" (F, G, 3),
        "looks" {count: [mask or screen points]}, "dense_s" {count: [s]}, "frames_done", "strands",
        "segments"}``.
    """
    import warp as wp

    from hairwarp.runner import Simulation
    from hairwarp.solver import SimulationFault

    out = {"status": "ok", "message": "", "frame_s": [], "tips": [], "looks": {n: [] for n in look_counts},
           "dense_s": {n: [] for n in dense_timing}, "frames_done": 0}
    try:
        sim = Simulation(scene, device=device)
    except Exception as exc:  # noqa: BLE001 - a variant that cannot be built is a result, not a crash
        out.update(status="error", message=f"{type(exc).__name__}: {exc}"[:400])
        return out
    G, S = sim.model.strand_count, sim.model.seg_per_strand
    out["strands"], out["segments"] = G, S
    dense = {n: _dense_for(sim, n) for n in sorted(set(look_counts) | set(dense_timing))}
    hermite_out = sim.scene.dense.basis == "linear"
    # On the CPU, the CPU time of this thread, where Warp's CPU kernels run: other programs on the cores, and
    # idle BLAS threads spinning after the look's numpy work, do not add to it. On a GPU, wall time to a sync.
    device_ = sim.model.device
    clock = time.perf_counter if device_.is_cuda else time.thread_time

    def sync():
        if device_.is_cuda:
            wp.synchronize_device(device_)

    for frame in range(1, frames + 1):
        sync()
        t0 = clock()
        try:
            sim.advance_frame()
            sync()
        except SimulationFault as fault:
            out.update(status="unstable", message=str(fault)[:400], fault_frame=frame)
            break
        out["frame_s"].append(clock() - t0)
        out["frames_done"] = frame
        out["tips"].append(sim.state.vertex_positions.numpy().reshape(G, S + 1, 3)[:, -1].copy())
        if frame in look_frames:
            for n, d in dense.items():
                if n in out["dense_s"]:
                    t0 = clock()
                    _dense_points(sim, d, hermite_out)  # ends in a copy to the host: synchronous
                    out["dense_s"][n].append(clock() - t0)
                if n in out["looks"]:
                    pts, counts = _dense_points(sim, d, True)
                    if grid is None:
                        from hairwarp.preview import _camera

                        right, up, _ = _camera(VIEW)
                        out["looks"][n].append((project(pts, right, up), pts, counts))
                    else:
                        out["looks"][n].append(coverage_mask(pts, counts, grid))
    out["tips"] = np.array(out["tips"])
    return out


def _cost(frame_s: list) -> float | None:
    kept = frame_s[WARMUP_FRAMES:] or frame_s
    return statistics.median(kept) if kept else None


def _compare(run: dict, ref: dict, ref_looks: list, count: int | None = None) -> dict:
    """Cost, tip error and mean IoU of ``run`` against ``ref`` (looks of ``count`` dense strands, default the
    first count the run rendered)."""
    row = {"status": run["status"], "message": run["message"], "frames_done": run["frames_done"],
           "cost_s": _cost(run["frame_s"]), "tip_rms_m": None, "iou": None}
    if "fault_frame" in run:
        row["fault_frame"] = run["fault_frame"]
    if run["status"] == "ok":
        row["tip_rms_m"] = tip_rms_error(run["tips"], ref["tips"])
        masks = run["looks"].get(count) if count is not None else next(iter(run["looks"].values()), [])
        if masks and ref_looks:
            row["iou"] = float(np.mean([silhouette_iou(a, b) for a, b in zip(masks, ref_looks, strict=True)]))
    return row


# ---------------------------------------------------------------------------------------------
# plans


def _ellipsoid_mesh_file(folder: Path, radii, subdivisions: int) -> tuple[Path, int]:
    """A PLY of the icosphere of ``subdivisions`` scaled to ``radii``, centred at the origin; its face count."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    mesh = trimesh.Trimesh(vertices=sphere.vertices * np.asarray(radii, float), faces=sphere.faces, process=False)
    path = folder / f"ellipsoid_{subdivisions}.ply"
    mesh.export(path)
    return path, len(mesh.faces)


def _capsule_mesh_file(folder: Path, radius: float, half_height: float) -> tuple[Path, int]:
    import trimesh

    mesh = trimesh.creation.capsule(height=2.0 * half_height, radius=radius, count=[16, 16])
    path = folder / "capsule.ply"
    mesh.export(path)
    return path, len(mesh.faces)


def _vec(v) -> str:
    return "[" + ", ".join(f"{float(x):.9g}" for x in v) + "]"


HEAD_SHIPPED = "analytic ellipsoid (shipped)"


def _head_options(scene, folder: Path, subdivisions=(2, 3, 4)) -> list:
    """The head as the analytic ellipsoid it ships, as icospheres scaled to its radii, and as the analytic sphere of
    its x semi-axis."""
    head = scene.head
    r = tuple(head.radii)
    opts = [(HEAD_SHIPPED, [])]
    for sub in subdivisions:
        path, faces = _ellipsoid_mesh_file(folder, r, sub)
        opts.append((f"ellipsoid mesh, {faces} triangles",
                     ['head.shape="mesh"', f'head.file="{path}"', f"head.translate={_vec(head.center)}"]))
    opts.append((f"analytic sphere r = {r[0]:g} m", ['head.shape="sphere"', f"head.radii={_vec((r[0],) * 3)}"]))
    return opts


def _shipped(path: Path) -> dict:
    """The scene file's sim.segments, sim.substeps and dense.count (schema defaults where unset), read without
    validating the file (the Ratboy scene's assets may be absent)."""
    import tomllib

    from hairwarp.scene import SCHEMA

    raw = tomllib.loads(Path(path).read_text())
    sim, dense = raw.get("sim", {}), raw.get("dense", {})
    return {"segments": int(sim.get("segments", SCHEMA["sim"].fields["segments"].default)),
            "substeps": int(sim.get("substeps", SCHEMA["sim"].fields["substeps"].default)),
            "dense": int(dense.get("count", SCHEMA["dense"].fields["count"].default))}


def plans(quick: bool, folder: Path, names=None) -> list[Plan]:
    """The scenes and their choices (full or quick sizes); mesh files of the collider variants go to ``folder``.

    The generated scenes' reference has 24 segments and 16 substeps (they shipped 20 and 8 when this suite was
    written): 31 segments leave the solver's bounds in long_hair's turn (a non-finite joint state at frame 17,
    with 32 substeps too), so it is a variant, not the reference. The options of each choice always include
    the scene's own value. Quick sizes cut the guide counts and the variants.
    """
    from hairwarp.scene import Scene

    want = set(names) if names else None
    ref24 = ["sim.segments=24", "sim.substeps=16"]

    def values(ref, shipped, options):
        return [ref] + sorted({*options, shipped} - {ref})

    def segments(shipped, ref, options):
        opts = [(f"{n}", [] if n == ref else [f"sim.segments={n}"]) for n in values(ref, shipped, options)]
        return Choice("segments", "sim.segments", opts, f"{shipped}")

    def substeps(shipped, ref, options):
        opts = [(f"{n}", [] if n == ref else [f"sim.substeps={n}"]) for n in values(ref, shipped, options)]
        return Choice("substeps", "sim.substeps", opts, f"{shipped}")

    def dense(shipped, options):
        return Choice("dense", "dense.count", [(f"{n}", [f"dense.count={n}"]) for n in sorted({*options, shipped})],
                      f"{shipped}", dense=True)

    def interactions():
        return [Choice("links", "links.enabled", [("on (shipped)", []), ("off", ["links.enabled=false"])],
                       "on (shipped)"),
                Choice("contacts", "interactions.enabled", [("on (shipped)", []),
                                                            ("off", ["interactions.enabled=false"])], "on (shipped)")]

    out = []
    if want is None or "long_hair" in want:
        path = ROOT / "scenes" / "long_hair.toml"
        sc, sh = Scene.load(path), _shipped(path)
        out.append(Plan("long_hair", path, ref24, 0.4 if quick else 1.3, [
            segments(sh["segments"], 24, (8,) if quick else (8, 12, 16, 20, 31)),
            substeps(sh["substeps"], 16, (4,) if quick else (2, 4, 8)),
            *([] if quick else [Choice("head collider", "head.shape", _head_options(sc, folder, (2, 3, 4)),
                                       HEAD_SHIPPED), *interactions()]),
            dense(sh["dense"], (1000,) if quick else (1000, 3000, 10000)),
        ], base=["groom.count=60"] if quick else [],
            notes=["1.3 s: still, then the turn to the side and most of the way back"]
            + (["quick: 60 guides (groom.count)"] if quick else [])))
    if want is None or "long_hair_shoulders" in want:
        path = ROOT / "scenes" / "long_hair_shoulders.toml"
        sc, sh = Scene.load(path), _shipped(path)
        cap = sc.colliders[0]
        cap_path, cap_faces = _capsule_mesh_file(folder, float(cap.radius), float(cap.half_height))
        choices = [substeps(sh["substeps"], 16, () if quick else (2, 4, 8))]
        if not quick:
            choices.insert(0, segments(sh["segments"], 24, (8, 12, 16, 20)))
            choices.append(Choice("head collider", "head.shape", _head_options(sc, folder, (3,)), HEAD_SHIPPED))
        choices.append(Choice("shoulder collider", "colliders[0].kind", [
            ("analytic capsule (shipped)", []),
            (f"capsule mesh, {cap_faces} triangles", ['colliders[0].kind="mesh"', f'colliders[0].file="{cap_path}"']),
        ], "analytic capsule (shipped)"))
        out.append(Plan("long_hair_shoulders", path, ref24, 0.5 if quick else 1.5, choices,
                        base=["groom.count=40"] if quick else [],
                        notes=["1.5 s: the nods and the landing on the shoulders (from 1.3 s the head holds still)",
                               "the scene writes no dense hair: its look is that of 3000 dense strands",
                               "where a wisp lands on the shoulder turns with the segment count, not converging in "
                               "it: at 16 substeps 20 against 24 segments 14.2 mm RMS (21 strands more than 20 mm "
                               "apart), 24 against 28 10.8 mm (11), 28 against 32 10.2 (10), 24 against 32 5.0 (0); "
                               "the segments' rows judge that branching more than a discretisation error (since the "
                               "body contacts' friction reaches its cone, 2026-12-06: 20 against 24 segments read "
                               "11.5 mm before, the shipped setting 9.25)"]
                        + (["quick: 40 guides (groom.count)"] if quick else [])))
    if want is None or "fast_turn" in want:
        path = ROOT / "scenes" / "fast_turn.toml"
        sh = _shipped(path)
        out.append(Plan("fast_turn", path, ref24, 0.4 if quick else 0.7, [
            *([] if quick else [segments(sh["segments"], 24, (12, 20))]),
            substeps(sh["substeps"], 16, () if quick else (4, 8)),
            *interactions(),
            *([] if quick else [dense(sh["dense"], (1000, 3000, 10000))]),
        ], base=["groom.count=60"] if quick else [],
            notes=["the head collider is long_hair's (the same ellipsoid): that choice is measured there",
                   "0.7 s: still, the 90 deg turn (0.2-0.6 s) and the start of the way back"]
            + (["quick: 60 guides (groom.count)"] if quick else [])))
    if want is None or "ratboy_mohawk" in want:
        path = ROOT / "scenes" / "ratboy_mohawk.toml"
        sh = _shipped(path)
        cut = 40 if quick else 120
        out.append(Plan("ratboy_mohawk", path, ["sim.segments=31", "sim.substeps=32"], 0.5 if quick else 2.3, [
            *([] if quick else [segments(sh["segments"], 31, (16, 24))]),
            substeps(sh["substeps"], 32, () if quick else (8, 16)),
            *([] if quick else interactions()),
        ], base=[f"groom.max_strands={cut}"], notes=[
            f"every n-th guide, at most {cut} of 2,219 (groom.max_strands; the scene ships 450): the cost per "
            "frame scales with the guide count, the errors are per guide",
            "2.3 s: both turns and the shake",
            "31 segments are the groom's own vertices, the most the reference has without inventing any",
            "the collider is the 25,814-triangle body mesh, with no analytic counterpart: not varied",
            "the scene writes no dense hair: its look is that of 3000 dense strands"]))
    for plan in out:
        plan.quick = quick
    return out


def scene_skip_reason(plan: Plan) -> str | None:
    """Why a plan cannot run here (the Ratboy assets are shared data beside the checkout), or None."""
    if plan.name == "ratboy_mohawk":
        from hairwarp.benchmarks.common import ratboy_paths

        missing = [str(p) for p in ratboy_paths() if not p.exists()]
        if missing:
            return "needs the shared TressFX Ratboy assets: missing " + ", ".join(missing)
    return None


# ---------------------------------------------------------------------------------------------
# one scene


def bench_scene(plan: Plan, device: str = "cpu", log=lambda message: None, *, gate=None) -> dict:
    """Reference, floor, one-choice variants, the shipped and the combined settings; returns the scene's JSON
    data. ``gate``: a :class:`hairwarp.benchmarks.common.QuietGate` to wait on before each run (None: the CPU
    times need none)."""
    from hairwarp.scene import Scene

    def load(overrides):
        return Scene.load(plan.path, [*plan.base, *overrides])

    def timed(label, scene, **kw):
        seen = gate.wait() if gate is not None else {}
        t0 = time.perf_counter()
        r = run_scene(scene, frames, device=device, **kw)
        log(f"budget: {plan.name} {label}: {r['status']}, {_fmt_cost(_cost(r['frame_s']))}/frame, "
            f"{time.perf_counter() - t0:.1f} s")
        r["under_load"] = bool(seen.get("under_load", False))
        return r

    shipped_scene = load([])
    fps = float(shipped_scene.sim.fps)
    frames = max(3, int(round(plan.duration_s * fps)))
    n_looks = LOOK_FRAMES if not plan.quick else 3
    look_frames = tuple(sorted(set(np.linspace(frames / n_looks, frames, n_looks).round().astype(int))))
    scene_count = int(shipped_scene.dense.count) or LOOK_DENSE_COUNT
    dense_choice = next((c for c in plan.choices if c.dense), None)
    dense_counts = [int(o[1][0].split("=")[1]) for o in dense_choice.options] if dense_choice else []
    ref_count = max([scene_count, *dense_counts])
    look_counts = sorted({scene_count, ref_count, *dense_counts})

    # the reference: screen points first, then the grid that holds them all
    ref = timed("reference", load(plan.reference), look_frames=look_frames, look_counts=look_counts,
                dense_timing=tuple(dense_counts))
    if ref["status"] != "ok":
        return {"name": plan.name, "status": "reference " + ref["status"], "message": ref["message"],
                "reference": plan.reference}
    from hairwarp.preview import _camera

    right, up, _ = _camera(VIEW)
    all_xy = np.concatenate([xy for looks in ref["looks"].values() for xy, _, _ in looks])
    grid = Grid.around(all_xy, right, up)
    ref_masks = {n: [coverage_mask(p, c, grid) for _, p, c in looks] for n, looks in ref["looks"].items()}

    result = {"name": plan.name, "status": "ok", "scene": str(plan.path.relative_to(ROOT)),
              "reference": plan.reference, "base": plan.base, "frames": frames, "fps": fps,
              "simulated_s": frames / fps, "strands": ref["strands"], "look_frames": list(look_frames),
              "look_dense_count": scene_count, "grid": {"pixel_m": grid.pixel, "shape": list(grid.shape),
                                                          "view": VIEW},
              "reference_cost_s": _cost(ref["frame_s"]), "reference_under_load": ref["under_load"],
              "notes": plan.notes, "choices": []}
    # how far the reference moves when gravity changes by 1e-5 of itself: a deterministic change of that size
    # moves a tip by microns, so anything more is the run amplifying small differences (contacts, chaos), a
    # floor under every error below
    if not plan.quick:
        gravity = [f"sim.gravity={_vec(FLOOR_GRAVITY)}"]
        floor = timed("reference, gravity 1e-5 stronger", load([*plan.reference, *gravity]), look_frames=look_frames,
                      look_counts=(scene_count,), grid=grid)
        result["floor"] = {"overrides": gravity, **_compare(floor, ref, ref_masks[scene_count])}
        if floor["status"] == "ok":  # the same work as the reference's: the faster of the two runs' medians
            result["reference_cost_s"] = min(result["reference_cost_s"], _cost(floor["frame_s"]))
    for choice in plan.choices:
        rows = []
        for label, overrides in choice.options:
            if choice.dense:
                n = int(overrides[0].split("=")[1])
                iou = float(np.mean([silhouette_iou(a, b) for a, b in zip(ref_masks[n], ref_masks[ref_count],
                                                                           strict=True)]))
                dense_s = ref["dense_s"].get(n) or []
                row = {"label": label, "overrides": overrides, "status": "ok", "cost_s": min(dense_s) if dense_s
                       else None, "tip_rms_m": None, "iou": iou, "cost_kind": "dense output per frame"}
            elif not overrides:
                row = {"label": label, "overrides": [], "status": "ok", "cost_s": result["reference_cost_s"],
                       "tip_rms_m": 0.0, "iou": 1.0, "reference": True}
            else:
                run = timed(f"{choice.name} {label}", load([*plan.reference, *overrides]), look_frames=look_frames,
                            look_counts=(scene_count,), grid=grid)
                row = {"label": label, "overrides": overrides, **_compare(run, ref, ref_masks[scene_count]),
                       "under_load": run["under_load"]}
            row["shipped"] = label == choice.shipped
            rows.append(row)
        pick = cheapest_within(rows)
        for row in rows:
            row["cheapest_within_bound"] = row["label"] == pick
        result["choices"].append({"name": choice.name, "key": choice.key, "dense": choice.dense, "rows": rows,
                                  "cheapest": pick})

    # the shipped settings and the combined cheapest settings, against the same reference
    chosen = {}  # choice key -> (its row picked, the shipped row)
    for ch in result["choices"]:
        row = next((r for r in ch["rows"] if r["cheapest_within_bound"]), None)
        if row is None:
            continue
        shipped = next((r for r in ch["rows"] if r["shipped"]), None)
        if shipped is not None and within(shipped) and (row["cost_s"] > (1.0 - MIN_SAVING) * shipped["cost_s"]
                                                        or not applicable(row)):
            # a saving inside the timing scatter is no reason to leave the shipped setting, and a mesh file
            # made here for the variant is no value a scene file can take
            row = shipped
        chosen[ch["key"]] = (row, shipped, bool(ch["dense"]))
    shipped_run = None
    dropped = []
    while True:
        combined, dense_pick, picks = [], None, {}
        for key, (row, _, dense) in chosen.items():
            picks[key] = row["label"]
            if dense:
                dense_pick = int(row["overrides"][0].split("=")[1])
            else:
                combined += row["overrides"]
        # The shipped and the combined settings are judged like the one-choice variants: the look at the scene's
        # dense count against the reference's at that count. The dense count is a pass over the guides with no
        # effect on them, judged on its own; "iou_dense" adds it (the dense count of the setting against the
        # reference's densest hair).
        dense_n = dense_pick or scene_count
        counts = tuple(sorted({scene_count, dense_n}))
        if shipped_run is None:
            shipped_run = timed("as shipped", load([]), look_frames=look_frames, look_counts=counts, grid=grid)
            result["shipped"] = {"overrides": [], **_compare(shipped_run, ref, ref_masks[scene_count], scene_count),
                                 "under_load": shipped_run["under_load"]}
            if dense_choice is not None:
                result["shipped"]["iou_dense"] = (_mean_iou(shipped_run["looks"][scene_count], ref_masks[ref_count])
                                                  if shipped_run["status"] == "ok" else None)
        comb_run = timed("combined", load([*plan.reference, *combined]), look_frames=look_frames,
                         look_counts=counts, grid=grid)
        comb = {"overrides": combined, "picks": picks, "dense_count": dense_pick, "dropped": list(dropped),
                **_compare(comb_run, ref, ref_masks[scene_count], scene_count), "under_load": comb_run["under_load"]}
        if dense_choice is not None:
            comb["iou_dense"] = (_mean_iou(comb_run["looks"][dense_n], ref_masks[ref_count])
                                 if comb_run["status"] == "ok" else None)
        # The combined run checks that the picks do not add up past the bound: with a dense count other than the
        # scene's, that count must hold the look too, against the reference's densest hair. (The shipped setting is
        # judged as the choices are; its iou_dense is on record.)
        comb["within_bound"] = within(comb) and (dense_n == scene_count or comb.get("iou_dense") is None
                                                 or comb["iou_dense"] >= IOU_BOUND)
        # Picks that add up past the bound: the one nearest the bound on its own goes back to the shipped value
        # (errors add, so the pick with the least to spare is the likeliest to tip the sum), and the rest are
        # combined again, until they hold or none is left.
        changed = [key for key, (row, shipped, _) in chosen.items() if shipped is not None and row is not shipped]
        if comb["within_bound"] or not changed:
            break
        key = min(changed, key=lambda k: _margin(chosen[k][0]))
        dropped.append(key)
        chosen[key] = (chosen[key][1], chosen[key][1], chosen[key][2])
    result["combined"] = comb
    result["shipped"]["within_bound"] = within(result["shipped"])
    return result


def _margin(row: dict) -> float:
    """How far a choice's row lies inside the bound on its own: the smaller of its tip error's and its look's share
    of the room the bound leaves (1: no error, 0: at the bound)."""
    tip, iou = row.get("tip_rms_m"), row.get("iou")
    return min(1.0 if tip is None else 1.0 - tip / TIP_BOUND_M,
               1.0 if iou is None else (iou - IOU_BOUND) / (1.0 - IOU_BOUND))


def _mean_iou(masks, ref_masks) -> float:
    return float(np.mean([silhouette_iou(a, b) for a, b in zip(masks, ref_masks, strict=True)]))


def _fmt_cost(x) -> str:
    return "–" if x is None else f"{x * 1e3:.3g} ms"


# ---------------------------------------------------------------------------------------------
# suite


def suite_budget(config, out, log=lambda message: None, *, names=None) -> dict:
    """The ``budget`` suite of ``hairwarp bench``: every shipped scene (``names``: a subset) against its
    reference. ``config``: a :class:`hairwarp.benchmarks.common.BenchConfig`; ``out``: the output folder (the
    report draws :func:`chart_budget` there)."""
    quick, device = bool(config.quick), config.device
    scenes, skipped = [], []
    with tempfile.TemporaryDirectory(prefix="hairwarp-budget-") as tmp:
        for plan in plans(quick, Path(tmp), names):
            why = scene_skip_reason(plan)
            if why:
                log(f"budget: {plan.name} skipped: {why}")
                skipped.append({"name": plan.name, "reason": why})
                continue
            t0 = time.perf_counter()
            data = bench_scene(plan, device, log)  # CPU times: no need to wait for idle cores
            data["wall_s"] = round(time.perf_counter() - t0, 1)
            scenes.append(data)
    data = {"bounds": {"tip_rms_m": TIP_BOUND_M, "iou": IOU_BOUND, "pixel_m": PIXEL_M, "view": VIEW,
                       "look_frames": LOOK_FRAMES, "warmup_frames": WARMUP_FRAMES},
            "scenes": scenes, "skipped": skipped}
    return data  # the report draws the chart (report.write_report -> chart_budget)


CHART = "bench_budget.png"


def chart_budget(data: dict, path) -> Path:
    """Cost (x, log) against tip error (y, log) per scene, one marker series per choice, the bound as a line."""
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    from hairwarp.benchmarks.report import _pyplot

    plt = _pyplot()
    scenes = [s for s in data.get("scenes", []) if s.get("status") == "ok"]
    n = max(1, len(scenes))
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.8), squeeze=False)
    markers = "osD^vP*X"
    floor = 1.0e-4  # [m] where the reference (error 0) is drawn
    unstable = 1.0  # [m] where an unstable run is drawn
    for ax, s in zip(axes[0], scenes, strict=False):
        for i, ch in enumerate(c for c in s["choices"] if not c["dense"]):
            xs, ys, picked = [], [], []
            for r in ch["rows"]:
                if r.get("cost_s") is None or r.get("reference"):
                    continue
                xs.append(r["cost_s"] * 1e3)
                ys.append(max(r["tip_rms_m"], floor) if r["status"] == "ok" else unstable)
                picked.append(r["cheapest_within_bound"])
            if not xs:
                continue
            dots = ax.scatter(xs, ys, marker=markers[i % len(markers)], label=ch["key"], alpha=0.8)
            px = [x for x, p in zip(xs, picked, strict=True) if p]
            py = [y for y, p in zip(ys, picked, strict=True) if p]
            ax.scatter(px, py, s=170, facecolors="none", edgecolors=dots.get_facecolor()[:1], linewidths=1.4)
        ax.plot([s["reference_cost_s"] * 1e3], [floor], "ks", ms=6, label="reference (error 0)")
        for key, m in (("shipped", "k+"), ("combined", "r*")):
            r = s.get(key)
            if r and r.get("cost_s") and r.get("tip_rms_m") is not None:
                ax.plot([r["cost_s"] * 1e3], [max(r["tip_rms_m"], floor)], m, ms=11, label=key)
        ax.axhline(TIP_BOUND_M, color="k", ls="--", lw=0.8, label=f"bound {TIP_BOUND_M * 1e3:g} mm")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(f"{s['name']} ({s['strands']} guides)")
        ax.set_xlabel("CPU ms per simulated frame")
        ax.set_ylabel("guide tip RMS error [m] (unstable: 1 m)")
        ax.legend(fontsize=6, loc="lower left")
    fig.suptitle("Cost against tip error, one choice changed from the reference; circled: the cheapest within "
                 "the bound", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------
# report


def _mm(x) -> str:
    return "–" if x is None else f"{x * 1e3:.3g}"


def _row_cells(r: dict) -> tuple[str, str, str]:
    if r.get("status") != "ok":
        where = f" at frame {r['fault_frame']}" if r.get("fault_frame") else ""
        return _mm(r.get("cost_s")), f"{r.get('status')}{where}", "–"
    iou = "–" if r.get("iou") is None else f"{r['iou']:.3f}"
    return _mm(r.get("cost_s")), "–" if r.get("tip_rms_m") is None else _mm(r["tip_rms_m"]), iou


def _override_text(overrides) -> str:
    shown = [o for o in overrides if "head.file" not in o and "colliders[0].file" not in o
             and "head.translate" not in o]
    return ", ".join(f"`{o}`" for o in shown) or "the reference"


def verdict(scene: dict) -> str:
    """What the figures say about the shipped scene: cheaper setting found, shipped is it, or out of bound."""
    shipped, comb = scene.get("shipped", {}), scene.get("combined", {})
    shipped_labels = {ch["key"]: next((r["label"] for r in ch["rows"] if r.get("shipped")), None)
                      for ch in scene.get("choices", [])}
    changed = {k: v for k, v in comb.get("picks", {}).items() if v != shipped_labels.get(k)}
    if not changed and shipped.get("within_bound"):
        return "the shipped setting meets the bound and is the pick of every choice"
    if changed and comb.get("within_bound") and shipped.get("within_bound") is not None:
        picks = ", ".join(f"`{k}` {v}" for k, v in changed.items())
        ratio = (f" at {comb['cost_s'] / shipped['cost_s']:.2g}× the shipped cost" if comb.get("cost_s")
                 and shipped.get("cost_s") else "")
        kept = comb.get("dropped") or []
        return (f"the combined setting ({picks} instead of the shipped values) meets the bound{ratio}"
                + (f" ({', '.join(f'`{k}`' for k in kept)} kept as shipped: with every pick together the run "
                   f"passed the bound)" if kept else "")
                + ("; the shipped one does not" if not shipped.get("within_bound") else ""))
    if shipped.get("within_bound"):
        return "the shipped setting meets the bound; the combined picks do not"
    return "the shipped setting does not meet the bound against this reference"


def md_budget(data: dict) -> list[str]:
    """Section 5 of the report: per scene and choice, cost against tip error and look, the picks marked."""
    b = data.get("bounds", {})
    out = ["## 5. Model no more than a scene needs (`hairwarp bench budget`)", "",
           f"![budget]({CHART})", "",
           "Each shipped scene is run at a reference setting (more segments and substeps than it ships, its "
           "colliders and interactions as designed), then with ONE modelling choice changed at a time. Cost: CPU "
           "ms per simulated frame (CPU time of the simulating thread; on CUDA wall time to a sync; median of the "
           f"frames after the first {b.get('warmup_frames', WARMUP_FRAMES)}; for `dense.count` the output cost "
           "per frame: interpolation, push-out, curve points, copy to the host). Tip error: RMS over frames and "
           "guides of the guide tips' distance to the reference's. Look: intersection over union of the dense "
           f"hair's coverage masks ({_g_mm(b.get('pixel_m'))} mm pixels, the preview's `{b.get('view', VIEW)}` "
           "camera, "
           f"{b.get('look_frames', LOOK_FRAMES)} frames) against the reference's.", "",
           f"**Bounds: tip error ≤ {_g_mm(b.get('tip_rms_m'))} mm RMS and IoU ≥ {b.get('iou', IOU_BOUND):g}.** A "
           "guide tip within 1 cm of the reference's stays among its own wisp's dense strands (guides are about "
           "1 cm apart on the generated scalps, and the dense tips scatter by 5 mm besides); a tighter bound "
           "would judge the reference's own spread, since equally faithful settings (the head as a 1280- or a "
           "5120-triangle ellipsoid, 20 or 24 segments) differ by 5–7 mm. 95 % of the silhouette's pixels: a "
           "one-pixel change along the outline is a few per cent of it. ✓ marks a setting within both bounds, "
           "**bold** the cheapest of its choice; *floor*: the reference with gravity 1e-5 stronger, what the "
           "run's own sensitivity gives. The *combined* run takes every choice's pick together (errors add), "
           f"except a pick that saves less than {MIN_SAVING:.0%} of the shipped option's cost (the scatter of "
           "the timings) or is a mesh file written for the variant (no scene value); *shipped* is the scene as "
           "it is.", ""]
    for s in data.get("scenes", []):
        out += [f"### `{s['name']}`", ""]
        if s.get("status") != "ok":
            out += [f"Reference run failed: {s.get('status')} — {s.get('message')}", ""]
            continue
        fl = s.get("floor")
        floor = (f"; floor: tip {_mm(fl.get('tip_rms_m'))} mm, IoU {fl['iou']:.3f}" if fl and fl.get("iou")
                 is not None else "")
        out += [f"{s['strands']} guides, {s['frames']} frames ({s['simulated_s']:.2f} s); reference "
                f"{', '.join(f'`{o}`' for o in [*s.get('base', []), *s['reference']])}: "
                f"{_mm(s['reference_cost_s'])} ms/frame{floor}. "
                + " ".join(n[0].upper() + n[1:] + "." for n in s.get("notes", [])), "",
                "| choice | setting | CPU ms / frame | tip RMS [mm] | IoU | |", "|---|---|---|---|---|---|"]
        for ch in s["choices"]:
            for r in ch["rows"]:
                cost, tip, iou = _row_cells(r)
                label = f"**{r['label']}**" if r.get("cheapest_within_bound") else r["label"]
                marks = ("✓" if within(r) else "") + (" shipped" if r.get("shipped") else "") + \
                        (" reference" if r.get("reference") else "")
                out.append(f"| `{ch['key']}` | {label} | {cost}{' (dense)' if ch['dense'] else ''} | {tip} | "
                           f"{iou} | {marks.strip()} |")
        for key in ("shipped", "combined"):
            r = s.get(key)
            if not r:
                continue
            cost, tip, iou = _row_cells(r)
            if r.get("iou_dense") is not None:
                iou += f" ({r['iou_dense']:.3f} with its dense count against the densest)"
            what = "as shipped" if key == "shipped" else f"combined: {_override_text(r['overrides'])}" + (
                f", `dense.count={r['dense_count']}`" if r.get("dense_count") else "")
            out.append(f"| **{key}** | {what} | {cost} | {tip} | {iou} | {'✓' if r.get('within_bound') else '✗'} |")
        out += ["", f"Verdict: {verdict(s)}.", ""]
    for sk in data.get("skipped", []):
        out += [f"- `{sk['name']}` skipped: {sk['reason']}."]
    return out


def _g_mm(x) -> str:
    return "–" if x is None else f"{x * 1e3:g}"


def summary_budget(data: dict) -> str:
    """One line for the report's summary."""
    parts = []
    for s in data.get("scenes", []):
        if s.get("status") != "ok":
            parts.append(f"{s['name']}: reference {s.get('status')}")
            continue
        c = s.get("combined", {})
        parts.append(f"{s['name']}: shipped {'within' if s.get('shipped', {}).get('within_bound') else 'outside'}, "
                     f"combined {_override_text(c.get('overrides', []))} "
                     f"{'within' if c.get('within_bound') else 'outside'}")
    b = data.get("bounds", {})
    return (f"- Model budget (tip ≤ {_g_mm(b.get('tip_rms_m'))} mm, IoU ≥ {b.get('iou', IOU_BOUND):g}): "
            + "; ".join(parts) + ".")
