"""The farm: wedges and shot batches, many runs of a scene (or many scenes), one Dask task each.

A *wedge* sweeps scene keys over lists of values (every combination, ``grid``, or the lists side by side,
``zip``); a *batch* runs several scenes (shots). Every run is a task of ``dask.distributed``: by default on a
``LocalCluster`` of single-threaded worker processes, one per core this process may use, or on any Dask cluster
given by its scheduler address (SLURM, Kubernetes, cloud through ``dask-jobqueue`` or ``dask-kubernetes``; the
workers need hairwarp installed and the output folder on a file system they share with this process).

Each task writes into its own folder ``OUT/<name>_<index>/``: the cache and the preview of
:func:`hairwarp.runner.simulate`, ``scene.json`` (the resolved scene it ran), ``stats.json`` (the record: status,
frames, wall time, the fault's message, broken links, contacts, tip travel) and, last, the completion marker
``complete.json``. When every task is back, ``OUT/summary.csv``, ``summary.md``, ``summary.json`` and the contact
sheet ``OUT/sheet.png`` (one row per run, the same frames in every row) are written.

Farm behaviour:

- a :class:`hairwarp.SimulationFault` is a result: the record says ``fault`` with the message, the task is not
  retried, and the others go on;
- any other exception in a task (a full disk, a file gone) is retried up to ``retries`` times by Dask
  (``retries=`` of ``Client.submit``), then recorded as ``error``;
- a task whose worker dies (killed, out of memory, a lost node) is rescheduled on another worker by the scheduler,
  up to :data:`WORKER_LOSS_RETRIES` times on a local cluster (``distributed.scheduler.allowed-failures``; a remote
  scheduler keeps its own setting), then recorded as ``lost``;
- a task whose folder holds a completion marker with the same key (a hash of the resolved scene and the hairwarp
  version) and every file it lists (the cache's root layer and its clip layers too) at the size it lists is not
  run again: a rerun of a wedge only runs what is missing, partial, changed or lost. A fault is complete (the same
  scene faults the same way); an error or a loss is not;
- Ctrl-C cancels the tasks not yet finished and closes the client and the local cluster; finished tasks stay
  complete for the next run.
"""

from __future__ import annotations

import csv
import hashlib
import importlib.util
import itertools
import json
import math
import os
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hairwarp.bench import json_default

__all__ = ["INSTALL_HINT", "Task", "batch", "batch_tasks", "completed_record", "local_cores",
           "make_output_folder", "read_cache_frames", "run_task", "run_tasks", "scene_key", "wedge", "wedge_tasks"]

MARKER = "complete.json"
"""The completion marker of a task folder, written last: the key and the size of every output file."""
STATS = "stats.json"
"""The task's record (what :func:`run_task` returns), in its folder."""
SCENE_JSON = "scene.json"
"""The resolved scene the task ran (every value, defaults filled in), its overrides and its key."""
TASK_RETRIES = 2
"""Dask ``retries=`` of each task: reruns after an exception other than a simulation fault."""
WORKER_LOSS_RETRIES = 2
"""``distributed.scheduler.allowed-failures`` of a local cluster: reruns of a task whose worker died."""
SHEET_FRAMES = 4
"""Columns of the contact sheet: evenly spaced frames, the first and the last included."""
POLL_S = 0.5
"""How often the progress line is refreshed [s]."""
LOCAL_CLUSTER_CONFIG = {
    "distributed.scheduler.allowed-failures": WORKER_LOSS_RETRIES,
    # Each worker has one core and no spare one: its statistical profiler (a thread sampling the task's stack every
    # 10 ms, for the dashboard's profile page) is left off; it cost under 1 % of a task here, but it is all waste.
    "distributed.worker.profile.enabled": False,
    # Dask's own housekeeping, every process waking on its event loop: the loop's health check (20 ms by default),
    # the workers' memory monitor (100 ms) and the dashboard's system monitor (500 ms). Idle, a cluster of 2 workers
    # took 7.5 % of a core with the defaults, 1.35 % with these, and under a full wedge that share comes out of the
    # runs (Dask 2026.8). The memory monitor still reacts within half a second; the health check only logs.
    "distributed.admin.tick.interval": "500ms",
    "distributed.worker.memory.monitor-interval": "500ms",
    "distributed.admin.system-monitor.interval": "2s",
}
"""Dask settings of the local cluster (a remote scheduler and its workers keep their own)."""
INSTALL_HINT = 'pip install "dask[distributed]>=2024.1"'
"""What to run when Dask is missing."""

STATUS_OK, STATUS_FAULT, STATUS_ERROR, STATUS_LOST, STATUS_CANCELLED = "ok", "fault", "error", "lost", "cancelled"
SUMMARY_COLUMNS = ("index", "name", "status", "frames", "frames_planned", "seconds", "broken_links", "contacts_mean",
                   "contacts_max", "tip_travel_mean_m", "tip_travel_max_m", "skipped", "message", "scene", "cache",
                   "preview")


@dataclass
class Task:
    """One run: a resolved scene and the folder its outputs go to.

    Attributes:
        index: position in the wedge or batch (0 first).
        name: the folder's name, ``<scene name>_<index>``.
        folder: absolute path of the task's folder.
        scene: the :class:`hairwarp.Scene`, every override applied and validated.
        key: :func:`scene_key` of ``scene``: what a completion marker must match to be reused.
        values: the wedged keys and their validated values (empty for a batch shot).
        overrides: the ``key=value`` texts applied on top of the scene file.
        threads: CPU threads per run (``sim.threads``) when the engine sets them, else None.
    """

    index: int
    name: str
    folder: str
    scene: object
    key: str
    values: dict = field(default_factory=dict)
    overrides: list = field(default_factory=list)
    threads: int | None = None


# ----------------------------------------------------------------------------------------------
# keys and completion


def scene_key(scene) -> str:
    """SHA-256 of the resolved scene (every validated value, file paths absolute) and the hairwarp version.

    The CPU thread count (``sim.threads``) is left out: it changes how fast a run goes, not what it writes, so a
    rerun with another number of workers still reuses finished tasks.
    """
    from hairwarp import __version__

    data = scene.to_dict()
    data.get("sim", {}).pop("threads", None)
    payload = json.dumps({"scene": data, "hairwarp": __version__}, sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()


def completed_record(folder, key: str) -> dict | None:
    """The record of a finished task in ``folder`` whose key is ``key``, or None when it must run (again).

    Finished means: the marker exists, holds ``key``, and every file it lists exists with the size it lists (a
    truncated cache or a deleted preview makes the task partial).
    """
    folder = Path(folder)
    try:
        marker = json.loads((folder / MARKER).read_text())
        record = json.loads((folder / STATS).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or marker.get("key") != key:
        return None
    for name, size in dict(marker.get("files", {})).items():
        path = folder / name
        try:
            if path.stat().st_size != size:
                return None
        except OSError:
            return None
    return _with_paths(record, folder)


def _with_paths(record: dict, folder: Path) -> dict:
    """The record with absolute paths of the folder, cache and preview (stats.json stores file names)."""
    out = dict(record)
    out["folder"] = str(folder)
    for k in ("cache", "preview"):
        if out.get(k):
            out[k] = str(folder / out[k])
    return out


def _write_json(path: Path, data) -> None:
    """Write ``data`` as JSON through a temporary file and a rename, so a reader never sees half a file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1, default=json_default) + "\n")
    os.replace(tmp, path)


# ----------------------------------------------------------------------------------------------
# the task


def run_task(task: Task) -> dict:
    """Run one task on a worker and return its record (also written to ``stats.json`` in its folder).

    A complete folder (see :func:`completed_record`) is returned as it is, with ``skipped`` true. Otherwise the
    marker is removed first, the folder's old outputs after it, then the run writes the cache and preview, the
    record, and the marker last. A :class:`hairwarp.SimulationFault` becomes the record's ``fault`` and
    ``message``; any other exception propagates, for Dask to retry.
    """
    t_start = time.time()
    folder = Path(task.folder)
    done = completed_record(folder, task.key)
    if done is not None:
        done["skipped"] = True
        done["timing"] = {"t_start": t_start, "t_end": time.time()}
        return done
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MARKER).unlink(missing_ok=True)  # from here on the folder is partial until the new marker
    cache = folder / f"{task.name}.usdc"
    _clear_outputs(folder, cache)

    _init_warp()
    from hairwarp.runner import simulate
    from hairwarp.solver import SimulationFault

    scene = task.scene
    threads = task.threads
    if threads is None and not _sets_threads(task.overrides):
        threads = _WORKER_THREADS  # a run that names its own thread count keeps it
    if threads is not None:
        # a local worker has its share of the cores: the executor's default (every core) would oversubscribe them
        scene = scene.with_overrides([f"sim.threads={int(threads)}"])
    _write_json(folder / SCENE_JSON, {"key": task.key, "source": str(scene.source) if scene.source else None,
                                      "overrides": list(task.overrides), "scene": scene.to_dict()})
    planned = int(scene.sim.frames)
    record = {"index": task.index, "name": task.name, "scene": str(scene.source) if scene.source else scene.name,
              "values": dict(task.values), "overrides": list(task.overrides), "key": task.key,
              "status": STATUS_OK, "message": None, "frames": 0, "frames_planned": planned, "seconds": None,
              "broken_links": None, "contacts_mean": None, "contacts_max": None, "tip_travel_mean_m": None,
              "tip_travel_max_m": None, "cache": None, "preview": None, "notes": [], "threads": task.threads,
              "worker": _worker_address(), "skipped": False}
    t_sim = time.perf_counter()
    try:
        result = simulate(scene, cache, progress=False)
    except SimulationFault as fault:
        record.update(status=STATUS_FAULT, message=str(fault),
                      frames=max(int(fault.frame) - 1, 0) if fault.frame is not None else 0)
    else:
        record.update(frames=int(result.frames), notes=list(result.notes))
        if result.preview_path is not None and Path(result.preview_path).is_file():
            record["preview"] = Path(result.preview_path).name
        record.update(_frame_stats(result.frame_stats))
    record["seconds"] = round(time.perf_counter() - t_sim, 3)
    # A run that stopped on a fault keeps its complete frames in its working folder, not at the cache's path.
    written = cache if cache.is_file() else _partial_root(cache)
    if written.is_file():
        record["cache"] = str(written.relative_to(folder))
        record.update(_tip_travel(written))
    _write_json(folder / STATS, record)
    _write_json(folder / MARKER, {"key": task.key, "status": record["status"], "files": _file_sizes(folder)})
    out = _with_paths(record, folder)
    out["timing"] = {"t_start": t_start, "t_end": time.time(), "simulate_s": record["seconds"]}
    return out


def _partial_root(cache: Path) -> Path:
    """Where :func:`hairwarp.runner.simulate` leaves the frames of a run that did not finish."""
    return cache.with_name(cache.stem + ".partial") / cache.name


def _clear_outputs(folder: Path, cache: Path) -> None:
    """Remove what an earlier attempt of the task left: its record, scene, preview and cache (the root layer, its
    clips, the working folder with its checkpoints and lock). Dask runs a task again only once the earlier attempt's
    worker is gone, so its lock (which names a process on another machine, maybe) must not block the new one."""
    import shutil

    for name in (STATS, SCENE_JSON, cache.name, cache.with_suffix(".png").name):
        (folder / name).unlink(missing_ok=True)
    for name in (cache.stem + ".clips", cache.stem + ".partial"):
        if (folder / name).is_dir():
            shutil.rmtree(folder / name)


def _file_sizes(folder: Path) -> dict[str, int]:
    """Every file under ``folder`` but the marker (and temporary files): relative path -> size in bytes."""
    out = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.name != MARKER and ".tmp" not in path.name:
            out[str(path.relative_to(folder))] = path.stat().st_size
    return out


def _init_warp() -> None:
    """Initialise Warp in this worker process without its banner, nor the missing CUDA driver's warning on a CPU
    machine (a worker's output goes to the terminal, and a plain ``hairwarp run`` prints neither)."""
    import warp as wp

    from hairwarp.cli import _init_warp_quietly

    wp.config.quiet = True
    wp.config.log_level = getattr(wp, "LOG_WARNING", 30)
    _init_warp_quietly(wp)


def _ignore_interrupts() -> None:
    """A local worker leaves Ctrl-C to the process that started it: the terminal sends SIGINT to the whole process
    group, and the client cancels the tasks and closes the cluster in order (no traceback from every worker)."""
    import signal

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the worker's main thread: nothing to change there
        pass


def _limit_usd_threads(threads: int) -> None:
    """usd-core saves layers with a thread pool of its own, one thread per core unless told otherwise: a worker
    given one core's share would compete with the other workers' pools for their cores."""
    from pxr import Work

    Work.SetConcurrencyLimit(int(threads))


#: CPU threads of a run in this process when it is a local cluster's worker (its share of the cores), else None.
_WORKER_THREADS = None


def _local_worker_plugin(threads: int):
    """A Dask worker plugin (every worker of the local cluster, restarted ones too): Ctrl-C ignored, Warp quiet,
    usd-core's threads limited to the worker's share of the cores."""
    from distributed import WorkerPlugin

    class LocalWorker(WorkerPlugin):
        def setup(self, worker):
            global _WORKER_THREADS
            _ignore_interrupts()
            _init_warp()
            _limit_usd_threads(threads)
            _WORKER_THREADS = int(threads)

    return LocalWorker()


def _worker_address() -> str | None:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return None


def _frame_stats(frame_stats: list[dict]) -> dict:
    """Broken links at the last frame; mean and largest contact count over the frames."""
    out = {}
    broken = [s["broken_links"] for s in frame_stats if "broken_links" in s]
    if broken:
        out["broken_links"] = int(broken[-1])
    contacts = [s["contacts"] for s in frame_stats if "contacts" in s]
    if contacts:
        out["contacts_mean"] = round(float(sum(contacts)) / len(contacts), 1)
        out["contacts_max"] = int(max(contacts))
    return out


def _tip_travel(cache: Path) -> dict:
    """Path length of the strand tips over the frames in the cache [m], mean and largest over the strands.

    The guides are read back when the cache holds them, else the first curves in it.
    """
    import numpy as np
    from pxr import Usd, UsdGeom

    from hairwarp.io.usd_common import UsdFileError, _open_stage

    try:
        stage = _open_stage(cache)
    except UsdFileError:  # statistics of a cache that cannot be read are left out; the run's record says why
        return {}
    curves = [UsdGeom.BasisCurves(p) for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    if not curves:
        return {}
    prim = next((c for c in curves if c.GetPrim().GetName() == "guides"), curves[0])
    counts = np.asarray(prim.GetCurveVertexCountsAttr().Get(), dtype=np.int64)
    points = prim.GetPointsAttr()
    times = points.GetTimeSamples() or [Usd.TimeCode.Default()]
    tips = np.cumsum(counts) - 1
    travel = np.zeros(len(counts))
    last = None
    for t in times:
        tip = np.asarray(points.Get(t), dtype=np.float64)[tips]
        if last is not None:
            travel += np.linalg.norm(tip - last, axis=1)
        last = tip
    return {"tip_travel_mean_m": round(float(travel.mean()), 5), "tip_travel_max_m": round(float(travel.max()), 5)}


# ----------------------------------------------------------------------------------------------
# planning: variants and shots into tasks


def toml_text(value) -> str:
    """A Python value as the TOML text of an override (``1e-4``, ``"nod"``, ``[0, 0, -9.81]``, ``true``)."""
    import numpy as np

    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        v = float(value)
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, Sequence | np.ndarray):
        return "[" + ", ".join(toml_text(v) for v in value) + "]"
    raise ValueError(f"cannot write {value!r} ({type(value).__name__}) as a scene value")


def split_values(text: str) -> list[str]:
    """``1e-4,3e-4,[0, 0, 1]`` -> ``["1e-4", "3e-4", "[0, 0, 1]"]``: commas inside brackets or quotes stay."""
    out, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(text):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i].strip())
            start = i + 1
    out.append(text[start:].strip())
    return out


def combinations(params: Mapping[str, Sequence[str]], mode: str = "grid") -> list[list[tuple[str, str]]]:
    """The variants of a wedge: lists of (key, value text). ``grid``: every combination, the last key varying
    fastest; ``zip``: the i-th value of every key together (the lists must be equally long)."""
    keys = list(params)
    if not keys:
        raise ValueError("a wedge needs at least one key to vary, e.g. -w strands.bend_stiffness=1e-4,1e-3")
    lists = [list(params[k]) for k in keys]
    for k, values in zip(keys, lists):
        if not values or any(v == "" for v in values):
            raise ValueError(f"wedge key {k}: empty value in {','.join(values)!r}")
    if mode == "grid":
        combos = itertools.product(*lists)
    elif mode == "zip":
        lengths = {len(v) for v in lists}
        if len(lengths) > 1:
            sizes = ", ".join(f"{k} has {len(v)}" for k, v in zip(keys, lists))
            raise ValueError(f"--zip needs as many values for every key: {sizes}")
        combos = zip(*lists)
    else:
        raise ValueError(f"unknown wedge mode {mode!r}; choose grid or zip")
    return [list(zip(keys, combo)) for combo in combos]


def _load(scene, overrides: list[str]):
    """The scene (a path or a :class:`hairwarp.Scene`) with ``overrides``, validated, its colliders' files read as a
    run reads them (so a bad one is refused before anything runs)."""
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    if isinstance(scene, Scene):
        scene = scene.with_overrides(overrides) if overrides else scene
    else:
        scene = Scene.load(scene, overrides=overrides)
    Simulation.check_colliders(scene)
    return scene


def _plain(value):
    return value.to_dict() if hasattr(value, "to_dict") else list(value) if isinstance(value, tuple) else value


def _folder_name(scene_name: str, index: int, total: int) -> str:
    return f"{scene_name}_{index:0{len(str(max(total - 1, 0)))}d}"


def wedge_tasks(scene, params: Mapping[str, Sequence[str]], out, *, mode: str = "grid",
                overrides: Iterable[str] = ()) -> list[Task]:
    """Every variant of ``scene`` (a path or a :class:`hairwarp.Scene`) as a validated :class:`Task`.

    ``params``: key -> list of value texts (TOML). All variants are validated before any is returned; the
    problems of every variant are reported together.

    Raises:
        ValueError: bad keys or values (a :class:`hairwarp.SceneError` message naming the key), unequal lists
            for ``zip``.
    """
    variants = combinations(params, mode)
    fixed = list(overrides)
    out = Path(out).resolve()
    tasks, problems = [], []
    for i, variant in enumerate(variants):
        texts = [f"{k}={v}" for k, v in variant]
        try:
            s = _load(scene, fixed + texts)
        except ValueError as exc:
            if str(exc) not in problems:
                problems.append(str(exc))
            continue
        name = _folder_name(s.name, i, len(variants))
        values = {k: _plain(s[k]) for k, _ in variant}
        tasks.append(Task(i, name, str(out / name), s, scene_key(s), values, fixed + texts))
    if problems:
        raise ValueError("\n".join(problems))
    return tasks


def read_list(path) -> list[str]:
    """Scene paths of a list file, one a line (``#`` starts a comment), relative to the list file's folder."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise FileNotFoundError(f"{path.resolve()}: cannot read the list of scenes ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path.resolve()}: is no list of scenes (not UTF-8 text: byte {exc.start})") from None
    out = []
    for line in lines:
        line = line.split("#", 1)[0].strip()
        if line:
            p = Path(line).expanduser()
            out.append(str(p if p.is_absolute() else path.parent / p))
    return out


def batch_tasks(scenes: Sequence, out, *, overrides: Iterable[str] = ()) -> list[Task]:
    """One validated :class:`Task` per scene (paths, ``@list.txt`` files, or :class:`hairwarp.Scene` objects)."""
    expanded = []
    for s in scenes:
        if isinstance(s, str | os.PathLike) and str(s).startswith("@"):
            expanded += read_list(str(s)[1:])
        else:
            expanded.append(s)
    if not expanded:
        raise ValueError("a batch needs at least one scene")
    fixed = list(overrides)
    out = Path(out).resolve()
    tasks, problems = [], []
    for i, source in enumerate(expanded):
        try:
            s = _load(source, fixed)
        except ValueError as exc:
            problems.append(str(exc))
            continue
        name = _folder_name(s.name, i, len(expanded))
        tasks.append(Task(i, name, str(out / name), s, scene_key(s), {}, fixed))
    if problems:
        raise ValueError("\n".join(problems))
    return tasks


# ----------------------------------------------------------------------------------------------
# the engine


def local_cores() -> int:
    """Cores this process may run on (its CPU affinity), which a local cluster fills with one worker each."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not Linux
        return max(os.cpu_count() or 1, 1)


def threads_per_run(cores: int, workers: int) -> int:
    """CPU threads each run gets so that ``workers`` runs at once fill ``cores`` without oversubscribing."""
    return max(1, cores // max(workers, 1))


def _sets_threads(overrides) -> bool:
    """Whether ``overrides`` (``key=value`` strings) set ``sim.threads``."""
    return any(o.split("=", 1)[0].strip() == "sim.threads" for o in overrides)


def _threads_key_exists() -> bool:
    """Whether the scene schema has ``sim.threads`` (CPU threads of a run). This is the one place the engine
    decides to set it: to :func:`threads_per_run` on a local cluster, unless the wedge varies it itself."""
    from hairwarp.scene import SCHEMA

    return "threads" in SCHEMA["sim"].fields


class _Cluster:
    """A Dask client on ``scheduler`` (an address), or on a new ``LocalCluster`` of ``workers`` single-threaded
    worker processes; closes both."""

    def __init__(self, scheduler: str | None, workers: int | None, tasks: int, log):
        import logging

        import dask
        from distributed import Client, LocalCluster

        self.cluster = None
        self.local = scheduler is None
        if scheduler is not None:
            try:
                self.client = Client(scheduler, timeout="15s")
            except (OSError, TimeoutError) as exc:
                raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
            self.workers = max(len(self.client.nthreads()), 1)
            self.cores = None
        else:
            self.cores = local_cores()
            self.workers = int(workers) if workers else max(1, min(self.cores, tasks))
            # Dask's own log is kept to critical messages: every task's outcome is in its record, and a shutdown
            # after Ctrl-C would otherwise print the workers' failed heartbeats to the terminal.
            with dask.config.set(LOCAL_CLUSTER_CONFIG):
                self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                            dashboard_address=":0", silence_logs=logging.CRITICAL)
            self.client = Client(self.cluster)
            self.client.register_plugin(_local_worker_plugin(threads_per_run(self.cores, self.workers)),
                                        name="hairwarp-local-worker")
        self.client.run(_init_warp)  # before the progress line, so Warp's start-up messages do not cut through it
        services = self.client.scheduler_info().get("services", {})
        if "dashboard" in services and self._scheduler_has_bokeh():
            log(f"dashboard  {self.client.dashboard_link}")
        else:
            log("dashboard  unavailable (Dask's dashboard needs bokeh: pip install bokeh)")

    def _scheduler_has_bokeh(self) -> bool:
        """Without bokeh a scheduler still serves a page at the dashboard's address, saying to install it; ask the
        scheduler's process (a lambda, sent by value: a remote scheduler need not have hairwarp)."""
        try:
            return bool(self.client.run_on_scheduler(lambda: importlib.util.find_spec("bokeh") is not None))
        except Exception:  # noqa: BLE001 - an old or restricted scheduler: show the address and let it say
            return True

    def close(self):
        for closer in (self.client, self.cluster):
            if closer is None:
                continue
            try:
                closer.close()
            except Exception:  # noqa: BLE001 - closing after an interrupt or a lost scheduler: nothing left to do
                pass


class _Progress:
    """One line on stderr: done, running, failed, skipped, elapsed, time left; a line per change off a terminal."""

    def __init__(self, total: int, skipped: int, enabled: bool, stream=None):
        self.total, self.skipped, self.enabled = total, skipped, enabled
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.perf_counter()
        self._last = None

    def update(self, ran: int, running: int, failed: int, final: bool = False):
        if not self.enabled:
            return
        done = ran + self.skipped
        elapsed = time.perf_counter() - self.start
        left = self.total - done
        eta = "" if not ran or not left else f"  ~{elapsed / ran * left:.0f} s left"
        line = (f"{done}/{self.total} done  {running} running  {failed} failed"
                + (f"  ({self.skipped} complete before)" if self.skipped else "") + f"  {elapsed:.0f} s{eta}")
        state = (done, running, failed)
        if self.tty:
            self.stream.write("\r" + line.ljust(72) + ("\n" if final else ""))
        elif state != self._last or final:
            self.stream.write(line + "\n")
        self._last = state
        self.stream.flush()


def _log_to_stderr(message: str) -> None:
    sys.stderr.write(message + "\n")
    sys.stderr.flush()


def _failure_record(task: Task, status: str, message: str) -> dict:
    from hairwarp.io.usd_common import clean_usd_text

    message = clean_usd_text(message)  # one line, without usd-core's internals when a USD error is quoted
    return {"index": task.index, "name": task.name, "folder": task.folder,
            "scene": str(task.scene.source) if task.scene.source else task.scene.name, "values": dict(task.values),
            "overrides": list(task.overrides), "key": task.key, "status": status, "message": message, "frames": 0,
            "frames_planned": int(task.scene.sim.frames), "seconds": None, "cache": None, "preview": None,
            "skipped": False}


def make_output_folder(out) -> Path:
    """Create the output folder of a wedge or a batch (its parents too) and return its absolute path.

    Called before anything runs, so that an output that cannot be a folder is one sentence naming the path and what
    to do, not the traceback of ``mkdir``: a ``-o out/tiny.usdc`` that exists as a file (the ``-o`` of
    ``hairwarp run``, whose output is a file) raised ``FileExistsError``, and ``-o /proc/w`` printed a bare
    ``[Errno 2]``.

    Raises:
        ValueError: ``out`` is a file, or the system refused to create it (the reason it gave).
    """
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        folder = out.with_suffix("") if out.suffix else out.parent / f"{out.name}_runs"
        raise ValueError(f"{out} is a file; the output of a wedge or a batch is a folder (a subfolder per run, the "
                         f"summaries and the contact sheet): name a folder, such as {folder}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot create the output folder {out} ({exc.strerror or exc}): name a folder this "
                         f"user can create and write") from None
    return out


def run_tasks(tasks: Sequence[Task], out, *, scheduler: str | None = None, workers: int | None = None,
              retries: int = TASK_RETRIES, progress: bool = False, log: Callable[[str], None] | None = None,
              sheet: bool = True, shared_framing: bool = True,
              task_fn: Callable[[Task], dict] = run_task) -> list[dict]:
    """Run ``tasks`` on Dask, write the summaries and the contact sheet into ``out``; return the records.

    Args:
        tasks: from :func:`wedge_tasks` or :func:`batch_tasks`.
        out: the output folder (the tasks' folders are inside it).
        scheduler: a Dask scheduler address (``tcp://host:8786``); None starts a ``LocalCluster``.
        workers: worker processes of the local cluster; default one per core this process may use (at most one
            per task to run).
        retries: Dask retries of a task after an exception other than a simulation fault.
        progress: a progress line on stderr.
        log: where messages go (the dashboard address); default stderr when ``progress``, else nowhere.
        sheet: write the contact sheet ``sheet.png``.
        shared_framing: one camera framing for the whole sheet (a wedge); False frames each row alone (shots).
        task_fn: the function a worker runs per task (tests wrap :func:`run_task`).

    Raises:
        KeyboardInterrupt: after cancelling what was left and closing the client and the local cluster.
    """
    out = make_output_folder(out)
    if log is None:
        log = _log_to_stderr if progress else (lambda m: None)
    records: dict[int, dict] = {}
    for t in tasks:
        done = completed_record(t.folder, t.key)
        if done is not None:
            done["skipped"] = True
            records[t.index] = done
    pending = [t for t in tasks if t.index not in records]
    if pending:
        _run_on_dask(pending, records, len(tasks), scheduler, workers, retries, progress, log, task_fn)
    result = [records[t.index] for t in tasks]
    write_summary(result, out)
    if sheet:
        try:
            contact_sheet(result, out / "sheet.png", shared_framing=shared_framing)
        except (OSError, ValueError, RuntimeError) as exc:
            log(f"contact sheet not written: {exc}")
    return result


def _run_on_dask(pending, records, total, scheduler, workers, retries, progress, log, task_fn):
    from distributed.scheduler import KilledWorker

    show = _Progress(total, total - len(pending), progress)
    engine = _Cluster(scheduler, workers, len(pending), log)
    futures = {}
    try:
        if engine.local and engine.cores and _threads_key_exists():
            threads = threads_per_run(engine.cores, engine.workers)
            for t in pending:
                if not _sets_threads(t.overrides):
                    t.threads = threads
        received: dict = {}
        lock = threading.Lock()

        def on_done(future):
            with lock:
                received[future.key] = time.time()

        tag = uuid.uuid4().hex[:8]  # tasks of two wedges on one scheduler never share a key
        for t in pending:
            submitted = time.time()
            f = engine.client.submit(task_fn, t, key=f"hairwarp-{t.name}-{tag}", retries=retries, pure=False)
            f.add_done_callback(on_done)
            futures[f] = (t, submitted)
        remaining = set(futures)
        failed = 0
        while remaining:
            finished = [f for f in remaining if f.done()]
            for f in finished:
                remaining.discard(f)
                t, submitted = futures[f]
                if f.status == "finished":
                    rec = f.result()
                elif f.status == "cancelled":
                    rec = _failure_record(t, STATUS_CANCELLED, "cancelled")
                else:
                    exc = f.exception()
                    if isinstance(exc, KilledWorker):
                        rec = _failure_record(t, STATUS_LOST, f"its worker died on every try ({exc})")
                    else:
                        rec = _failure_record(t, STATUS_ERROR, f"{type(exc).__name__}: {exc}")
                timing = dict(rec.get("timing") or {})
                with lock:
                    timing.update(t_submit=submitted, t_received=received.get(f.key, time.time()))
                rec["timing"] = timing
                records[t.index] = rec
                failed += rec["status"] != STATUS_OK
            running = 0
            if remaining:
                try:
                    ours = {f.key for f in remaining}
                    busy = sum(1 for keys in engine.client.processing().values() for k in keys if k in ours)
                    running = min(busy, sum(engine.client.nthreads().values()))
                except (OSError, TimeoutError):
                    running = 0
            ran = len(records) - show.skipped
            show.update(ran, running, failed, final=not remaining)
            if remaining:
                time.sleep(POLL_S)
    except KeyboardInterrupt:
        left = [f for f in futures if not f.done()]
        if left:
            try:
                engine.client.cancel(left, force=True)
            except Exception:  # noqa: BLE001 - the scheduler may be gone; closing below ends the tasks anyway
                pass
        if show.enabled and show.tty:
            show.stream.write("\n")
        raise
    finally:
        engine.close()


# ----------------------------------------------------------------------------------------------
# summaries and the contact sheet


def write_summary(records: Sequence[dict], out) -> tuple[Path, Path, Path]:
    """``summary.csv`` (one row per run, one column per wedged key), ``summary.md`` and ``summary.json``."""
    out = Path(out)
    keys = list(dict.fromkeys(k for r in records for k in (r.get("values") or {})))
    columns = ["index", "name", *keys, *[c for c in SUMMARY_COLUMNS if c not in ("index", "name")]]
    csv_path = out / "summary.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in records:
            w.writerow([_cell((r.get("values") or {}).get(c)) if c in keys else _cell(r.get(c)) for c in columns])
    md = ["| # | name | " + " | ".join(f"`{k}`" for k in keys) + (" | " if keys else "")
          + "status | frames | wall [s] | broken links | contacts (mean / max) | tip travel mean / max [m] |",
          "|---:|---|" + "---|" * len(keys) + "---|---:|---:|---:|---:|---:|"]
    for r in records:
        status = r["status"] + (" (complete before)" if r.get("skipped") else "")
        contacts = "–" if r.get("contacts_mean") is None else f"{r['contacts_mean']:g} / {r['contacts_max']}"
        tips = ("–" if r.get("tip_travel_mean_m") is None
                else f"{r['tip_travel_mean_m']:.3g} / {r['tip_travel_max_m']:.3g}")
        md.append(f"| {r['index']} | {r['name']} | " + "".join(f"{_cell(r['values'].get(k))} | " for k in keys)
                  + f"{status} | {r.get('frames', 0)}/{r.get('frames_planned', '?')} | "
                  + f"{_cell(r.get('seconds')) or '–'} | {_cell(r.get('broken_links')) or '–'} | {contacts} | {tips} |")
    problems = [r for r in records if r.get("message")]
    if problems:
        md += ["", *[f"- **{r['name']}** ({r['status']}): {r['message']}" for r in problems]]
    noted = [(r["name"], note) for r in records for note in r.get("notes") or ()]
    if noted:  # what a run found on its way (frames taken again, links that would not hold the groom up)
        md += ["", "Notes of the runs:", "", *[f"- **{name}**: {note}" for name, note in noted]]
    md_path = out / "summary.md"
    md_path.write_text("\n".join(md) + "\n")
    json_path = out / "summary.json"
    _write_json(json_path, list(records))
    return csv_path, md_path, json_path


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_cell(x) for x in v) + "]"
    return str(v)


def read_cache_frames(path, frames: Sequence[float]) -> list[dict | None]:
    """Frames of a cache for pictures, read through USD: per frame ``{"curves": {name: (points, counts)},
    "meshes": [(vertices, triangles)]}`` in world space, or None where the cache has no such time sample. Frame
    ``f`` is the time code ``start + f``, ``start`` the stage's start time code (``output.start_frame``).

    Curves whose purpose is ``guide`` are left out when the cache also holds curves to render (dense hair).
    """
    import numpy as np
    from pxr import Usd, UsdGeom

    from hairwarp.io.usd_common import _open_stage

    stage = _open_stage(path)
    curves = [p for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    render = [p for p in curves if UsdGeom.Imageable(p).ComputePurpose() != UsdGeom.Tokens.guide]
    curves = render or curves
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    samples = set()
    for p in curves:
        samples.update(UsdGeom.BasisCurves(p).GetPointsAttr().GetTimeSamples())
    out = []
    start = stage.GetStartTimeCode() if stage.HasAuthoredTimeCodeRange() else 0.0
    for frame in (start + float(f) for f in frames):
        if samples and float(frame) not in samples:
            out.append(None)
            continue
        xf = UsdGeom.XformCache(Usd.TimeCode(float(frame)))
        tc = Usd.TimeCode(float(frame))
        data = {"curves": {}, "meshes": []}
        for p in curves:
            c = UsdGeom.BasisCurves(p)
            pts = np.asarray(c.GetPointsAttr().Get(tc), dtype=np.float64).reshape(-1, 3)
            counts = np.asarray(c.GetCurveVertexCountsAttr().Get(tc), dtype=np.int64)
            data["curves"][p.GetName()] = (_to_world(pts, xf.GetLocalToWorldTransform(p)), counts)
        for p in meshes:
            m = UsdGeom.Mesh(p)
            pts = np.asarray(m.GetPointsAttr().Get(tc), dtype=np.float64).reshape(-1, 3)
            counts = np.asarray(m.GetFaceVertexCountsAttr().Get(tc), dtype=np.int64)
            index = np.asarray(m.GetFaceVertexIndicesAttr().Get(tc), dtype=np.int64)
            data["meshes"].append((_to_world(pts, xf.GetLocalToWorldTransform(p)), _fan_triangles(counts, index)))
        out.append(data)
    return out


def _to_world(points, matrix):
    import numpy as np

    m = np.array(matrix, dtype=np.float64)  # USD: row vectors, p_world = p @ M[:3, :3] + M[3, :3]
    return points @ m[:3, :3] + m[3, :3]


def _fan_triangles(counts, index):
    """Triangles of polygons given by face vertex counts and indices (a fan per polygon)."""
    import numpy as np

    tris = []
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for n in np.unique(counts):
        if n < 3:
            continue
        first = starts[counts == n]
        for k in range(1, n - 1):
            tris.append(np.stack([index[first], index[first + k], index[first + k + 1]], axis=1))
    return np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)


def sheet_frames(records: Sequence[dict], columns: int = SHEET_FRAMES) -> list[int]:
    """The frames every row of a wedge's sheet shows: evenly spaced over the longest planned run."""
    import numpy as np

    last = max((int(r.get("frames_planned") or 0) for r in records), default=0)
    return sorted({int(round(x)) for x in np.linspace(0, last, min(columns, last + 1))})


def _row_title(r: dict) -> str:
    """A row's caption on the sheet: the run's name, each wedged key in full with its value (the last name alone
    made ``strands.damping`` and ``links.damping`` both ``damping``), or the shot's scene file, and its status."""
    lines = [r["name"]]
    for k, v in (r.get("values") or {}).items():
        lines.append(f"{k} = {_cell(v)}")
    if not r.get("values"):
        lines.append(Path(str(r.get("scene", ""))).name)
    status = r["status"]
    if status == STATUS_FAULT:
        status = f"fault after frame {r.get('frames', 0)}"
    lines.append(status)
    return "\n".join(lines)


def contact_sheet(records: Sequence[dict], out_png, *, columns: int = SHEET_FRAMES, shared_framing: bool = True,
                  panel_px=(260, 260)) -> Path:
    """One row per run, the same frames in every row (a wedge) or each shot's own evenly spaced frames
    (``shared_framing`` False), drawn with :func:`hairwarp.preview.render_grid`."""
    import numpy as np

    from hairwarp.preview import render_grid

    common = sheet_frames(records, columns)
    rows, titles, colors = [], [], []
    for r in records:
        if shared_framing:
            frames = common
        else:
            last = int(r.get("frames_planned") or 0)
            frames = sorted({int(round(x)) for x in np.linspace(0, last, min(columns, last + 1))})
        cache = r.get("cache")
        row = read_cache_frames(cache, frames) if cache and Path(cache).is_file() else [None] * len(frames)
        rows.append(row)
        titles.append(_row_title(r))
        colors.append(None if r["status"] == STATUS_OK else "#a33")
    col_titles = [f"frame {f}" for f in common] if shared_framing else None
    return render_grid(rows, out_png, row_titles=titles, col_titles=col_titles, shared_limits=shared_framing,
                       row_colors=colors, panel_px=panel_px)


# ----------------------------------------------------------------------------------------------
# the Python API


def wedge(scene, params: Mapping[str, Sequence], *, mode: str = "grid", out=None, scheduler: str | None = None,
          workers: int | None = None, overrides: Iterable[str] = (), retries: int = TASK_RETRIES,
          progress: bool = False, sheet: bool = True) -> list[dict]:
    """Run every variant of ``scene`` with Dask and return their records (the rows of ``summary.csv``).

    Example::

        records = hw.wedge("scenes/long_hair.toml",
                           {"strands.bend_stiffness": [1e-4, 3e-4, 1e-3], "links.stiffness": [0.2, 0.35]},
                           out="out/wedge", overrides=["sim.frames=30"])

    Args:
        scene: a scene file or a :class:`hairwarp.Scene`.
        params: scene key -> list of values (Python values, written as TOML).
        mode: ``grid`` (every combination) or ``zip`` (the i-th values together; equal lengths).
        out: the output folder; default ``out/wedge_<scene name>``.
        scheduler: a Dask scheduler address; None starts a local cluster.
        workers: worker processes of the local cluster (default: one per core this process may use).
        overrides: ``key=value`` texts applied to every variant (``sim.frames=30``).
        retries: Dask retries after an exception other than a simulation fault.
        progress: a progress line on stderr.
        sheet: write the contact sheet ``sheet.png``.

    Returns:
        One dict per variant, in order: ``status`` (``ok``, ``fault``, ``error``, ``lost``), ``message``,
        ``values``, ``frames``, ``seconds``, ``broken_links``, ``contacts_mean``, ``contacts_max``,
        ``tip_travel_mean_m``, ``tip_travel_max_m``, ``cache``, ``preview``, ``folder``, ``skipped``, ...
    """
    texts = {k: [toml_text(v) for v in ([vs] if isinstance(vs, str) or not hasattr(vs, "__iter__") else vs)]
             for k, vs in params.items()}
    base = _load(scene, list(overrides))
    out = Path(out) if out is not None else Path("out") / f"wedge_{base.name}"
    tasks = wedge_tasks(scene, texts, out, mode=mode, overrides=overrides)
    return run_tasks(tasks, out, scheduler=scheduler, workers=workers, retries=retries, progress=progress,
                     sheet=sheet, shared_framing=True)


def batch(scenes: Sequence, *, out=None, scheduler: str | None = None, workers: int | None = None,
          overrides: Iterable[str] = (), retries: int = TASK_RETRIES, progress: bool = False,
          sheet: bool = True) -> list[dict]:
    """Run several scenes (shots: paths, ``@list.txt`` files or :class:`hairwarp.Scene` objects) with Dask and
    return their records; the arguments are those of :func:`wedge` (default ``out``: ``out/batch``)."""
    out = Path(out) if out is not None else Path("out") / "batch"
    tasks = batch_tasks(scenes, out, overrides=overrides)
    return run_tasks(tasks, out, scheduler=scheduler, workers=workers, retries=retries, progress=progress,
                     sheet=sheet, shared_framing=False)
