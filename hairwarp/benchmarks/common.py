"""Shared pieces of the benchmark suites: the canonical scene, the timing protocol, child processes,
the machine description and the settings of a run."""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

# The canonical benchmark scene of the peers' study: 0.3 m strands of solid cylinders, roots on a
# 1 cm grid at z = 1, first joint turned 80 degrees about +y, gravity, joint damping 1e-10 N m s/rad.
STRAND_LENGTH = 0.3
RADIUS = 2.0e-3
DENSITY = 1300.0
GRAVITY = 9.81
TILT_DEG = 80.0
ROOT_SPACING = 0.01
ROOT_Z = 1.0
JOINT_DAMPING = 1.0e-10
BENCH_DT = 1.0e-3

RESULT_TAG = "@@RESULT@@"


def tilt_direction(tilt_deg: float = TILT_DEG) -> np.ndarray:
    """Unit vector root -> tip of a straight strand whose root joint is turned ``tilt_deg`` about +y."""
    a = math.radians(tilt_deg)
    return np.array([-math.sin(a), 0.0, -math.cos(a)])


def root_grid(strands: int, spacing: float = ROOT_SPACING, z: float = ROOT_Z) -> np.ndarray:
    """Roots (G, 3) on a square grid, row by row, as the peers place them."""
    side = max(1, int(math.ceil(math.sqrt(strands))))
    i = np.arange(strands)
    return np.stack([(i % side) * spacing, (i // side) * spacing, np.full(strands, z)], axis=1)


def straight_strands(roots: np.ndarray, segments: int, direction, length: float = STRAND_LENGTH) -> np.ndarray:
    """Vertices (G, S+1, 3) of straight strands from ``roots`` along ``direction``."""
    k = np.arange(segments + 1)[:, None] * (length / segments)
    return np.asarray(roots, float)[:, None, :] + k[None] * np.asarray(direction, float)[None, None, :]


def canonical_vertices(strands: int, segments: int) -> np.ndarray:
    """The canonical scene's initial vertices (G, S+1, 3)."""
    return straight_strands(root_grid(strands), segments, tilt_direction())


def segment_mass(segments: int, length: float = STRAND_LENGTH) -> float:
    seg = length / segments
    return DENSITY * math.pi * RADIUS**2 * seg


def segment_inertia(segments: int, length: float = STRAND_LENGTH) -> np.ndarray:
    """Principal moments about the centre of mass (x, y, z) of one solid-cylinder segment, axis z."""
    m, r, L = segment_mass(segments, length), RADIUS, length / segments
    perp = m * (3.0 * r * r + L * L) / 12.0
    return np.array([perp, perp, 0.5 * m * r * r])


# ---------------------------------------------------------------------------------------------
# timing


def time_blocks(step, sync=lambda: None, *, steps: int = 100, blocks: int = 3, warmup: int = 3,
                budget_s: float = 10.0) -> dict:
    """The peers' timing protocol: one first step, ``warmup`` untimed steps, then ``blocks`` timed blocks.

    ``step(k)`` advances by k steps. A block has ``steps`` steps unless ``blocks * steps`` times the
    warm-up estimate exceeds ``budget_s``; then the block is halved (``downsized``) until it fits.

    Returns:
        ``{"first_step_s", "step_s" (median over blocks of block time / steps), "step_s_min",
        "timed_steps", "blocks", "block_steps", "downsized"}``.
    """
    t0 = time.perf_counter()
    step(1)
    sync()
    first = time.perf_counter() - t0
    n = max(1, warmup)
    t0 = time.perf_counter()
    step(n)
    sync()
    estimate = (time.perf_counter() - t0) / n
    k, downsized = max(1, steps), False
    while k * blocks * estimate > budget_s and k > 1:
        k = max(1, k // 2)
        downsized = True
    per = []
    for _ in range(blocks):
        t0 = time.perf_counter()
        step(k)
        sync()
        per.append((time.perf_counter() - t0) / k)
    return {
        "first_step_s": first,
        "step_s": statistics.median(per),
        "step_s_min": min(per),
        "timed_steps": k * blocks,
        "blocks": blocks,
        "block_steps": k,
        "downsized": downsized,
    }


def fit_exponent(x, y) -> float | None:
    """Least-squares slope of log y against log x (the exponent p of y ~ x^p); None with < 2 points."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 2 or np.unique(x[ok]).size < 2:
        return None
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


# ---------------------------------------------------------------------------------------------
# child processes


def run_child(request: dict, timeout_s: float) -> dict:
    """Run one peer measurement in a fresh interpreter; never raises.

    The child is ``python -m hairwarp.bench --child JSON``; it prints one line ``@@RESULT@@{...}``.
    A timeout, a crash or a missing result gives ``{"status": "timeout" | "error", "message": ...}``.
    """
    cmd = [sys.executable, "-m", "hairwarp.bench", "--child", json.dumps(request)]
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    # run in a scratch folder (MuJoCo writes MUJOCO_LOG.TXT into the working directory) with the
    # package importable from there
    package_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH")) if p)
    t0 = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(prefix="hairwarp-bench-") as scratch:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env, cwd=scratch)
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "message": f"no result within {timeout_s:.0f} s",
                "wall_s": round(time.perf_counter() - t0, 2)}
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_TAG):
            result = json.loads(line[len(RESULT_TAG):])
            result.setdefault("wall_s", round(time.perf_counter() - t0, 2))
            return result
    tail = (proc.stderr or proc.stdout)[-800:]
    signal = f" (signal {-proc.returncode})" if proc.returncode < 0 else ""
    cause = next((ln.strip() for ln in tail.splitlines() if "Assertion failed" in ln or "Error" in ln), "")
    return {"status": "error",
            "message": f"child exited with code {proc.returncode}{signal} and no result" + (f": {cause}" if cause
                                                                                             else ""),
            "stderr_tail": tail, "wall_s": round(time.perf_counter() - t0, 2)}


def child_result(fn, request: dict) -> dict:
    """Call ``fn(request)`` in a child and wrap the outcome: ok, absent (a package is missing) or error."""
    t0 = time.perf_counter()
    try:
        out = {"status": "ok", **fn(request)}
    except ModuleNotFoundError as exc:
        out = {"status": "absent", "message": f"package {exc.name!r} is not installed"}
    except Exception as exc:  # noqa: BLE001 - one failing peer must not stop the run
        out = {"status": "error", "message": f"{type(exc).__name__}: {exc}"[:600]}
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    return out


# ---------------------------------------------------------------------------------------------
# other programs on a shared machine


def _cpu_times():
    try:
        with open("/proc/stat") as f:
            fields = [float(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)
    return sum(fields[:8]), idle


def busy_cores(window_s: float = 0.3) -> float | None:
    """Cores kept busy over ``window_s`` by everything on the machine (this process is idle meanwhile)."""
    a = _cpu_times()
    if a is None:
        return None
    time.sleep(window_s)
    b = _cpu_times()
    total, idle = b[0] - a[0], b[1] - a[1]
    return (total - idle) / total * (os.cpu_count() or 1) if total > 0 else 0.0


class QuietGate:
    """Waits, before a timing, until other programs leave the machine's cores alone.

    A timing starts once fewer than ``threshold`` cores are busy (others' work: this process is
    idle while it looks), or when the wait for that timing or the whole run's ``budget_s`` is spent;
    every call records what it saw, so a figure taken under load can be told apart.
    """

    def __init__(self, budget_s: float = 120.0, threshold: float = 0.35, max_wait_s: float = 30.0):
        self.enabled = True
        self.budget_s, self.threshold, self.max_wait_s = budget_s, threshold, max_wait_s
        self.reset()

    def reset(self):
        self.waited_s = 0.0
        self.loaded = 0
        self.timings = 0

    def wait(self) -> dict:
        if not self.enabled:
            return {"others_busy_cores": None, "waited_s": 0.0, "under_load": False}
        self.timings += 1
        t0 = time.perf_counter()
        busy = busy_cores()
        while (busy is not None and busy >= self.threshold and time.perf_counter() - t0 < self.max_wait_s
               and self.waited_s + time.perf_counter() - t0 < self.budget_s):
            time.sleep(0.7)
            busy = busy_cores()
        waited = time.perf_counter() - t0
        self.waited_s += waited
        loaded = busy is not None and busy >= self.threshold
        self.loaded += int(loaded)
        return {"others_busy_cores": None if busy is None else round(busy, 2), "waited_s": round(waited, 2),
                "under_load": loaded}

    def summary(self) -> dict:
        return {"enabled": self.enabled, "waited_s": round(self.waited_s, 1), "timings": self.timings,
                "timings_under_load": self.loaded, "threshold_cores": self.threshold}


GATE = QuietGate()


# ---------------------------------------------------------------------------------------------
# the machine


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(dist: str) -> str | None:
    import importlib.metadata as md

    try:
        return md.version(dist)
    except md.PackageNotFoundError:
        return None


def _git_commit() -> str | None:
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        out = subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_words(sm: dict) -> str:
    """Where a suite ran, for its section's footer (" on AMD EPYC, 2 cores"): a report gathers suites run at
    different times, and not always on the same kind of machine."""
    if not sm.get("cpu"):
        return ""
    return f" on {sm['cpu']}" + (f", {sm['cores']} cores" if sm.get("cores") else "")


def machine_info() -> dict:
    """CPU, cores, Python and package versions, date, load average: what a figure depends on."""
    import warp as wp

    from hairwarp import __version__

    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "hairwarp": __version__,
        "git_commit": _git_commit(),
        "versions": {
            "warp": wp.config.version,
            "numpy": np.__version__,
            "pin": _version("pin"),
            "mujoco": _version("mujoco"),
            "newton": _version("newton"),
            "matplotlib": _version("matplotlib"),
            "scipy": _version("scipy"),
        },
        "load_average_start": load_average(),
        "cuda_devices": [str(d) for d in wp.get_cuda_devices()] if wp.is_cuda_available() else [],
    }


# ---------------------------------------------------------------------------------------------
# settings of a run


@dataclass
class BenchConfig:
    """Sizes and time boxes of every suite; ``full()`` and ``quick()`` are the two presets."""

    quick: bool = False
    device: str = "cpu"
    threads: int = 0  # CPU threads of the threads suite's N-thread runs; 0: every core this process may use
    # dynamics
    dyn_configs: list = field(default_factory=lambda: [(100, 20), (1000, 20), (100, 50)])
    dyn_integrators: tuple = ("semi_implicit", "implicit_joints")
    dyn_peers: tuple = ("pinocchio", "pinocchio_parallel", "mujoco_euler", "mujoco_rollout_euler_t0",
                        "mujoco_rollout_euler_threads", "newton_featherstone_tile", "newton_vbd")
    block_steps: int = 100
    blocks: int = 3
    warmup: int = 3
    ours_budget_s: float = 4.0
    peer_budget_s: float = 8.0
    peer_timeout_s: float = 240.0
    graph_block: int = 10
    # accuracy
    acc_ref_dt: float = 1.0e-5
    acc_duration: float = 1.0
    acc_dts: tuple = (1e-3, 5e-4, 2e-4, 1e-4, 5e-5, 2e-5, 1e-5)
    acc_integrators: tuple = ("semi_implicit", "implicit_joints", "rk4")
    acc_peer_dts: dict = field(default_factory=lambda: {
        "pinocchio_euler": (1e-3, 5e-4, 2e-4, 1e-4, 5e-5, 2e-5),
        "mujoco_euler": (1e-3, 5e-4, 2e-4, 1e-4, 5e-5, 2e-5),
        "mujoco_implicitfast": (1e-3, 5e-4, 2e-4, 1e-4, 5e-5),
        "mujoco_rk4": (1e-3, 5e-4, 2e-4, 1e-4, 5e-5),
        # MuJoCo 4's discrete step map: joint springs and damping implicit, as in implicit_joints
        "mujoco_discrete": (1e-3, 5e-4, 2e-4, 1e-4, 5e-5),
        "newton_featherstone_tile": (1e-3, 5e-4, 2.5e-4),
        "newton_vbd": (1e-3, 5e-4, 2.5e-4),
    })
    acc_cost_strands: int = 100
    conv_segments: tuple = (5, 10, 20, 40, 80)
    conv_bend_stiffness: float = 1.0e-3
    # stability
    stab_stiffness: tuple = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1)
    stab_integrators: tuple = ("semi_implicit", "implicit_joints", "rk4")
    stab_mujoco: tuple = ("Euler", "implicitfast", "discrete")
    stab_mujoco_stiffness: tuple = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
    # Newton's VBD rods cost ~1 ms a step from Python: three stiffnesses, steps no smaller than stab_newton_min_dt
    stab_newton_stiffness: tuple = (1e-5, 1e-3, 1e-1)
    stab_newton_min_dt: float = 1.0e-4
    stab_newton_duration: float = 0.5
    stab_duration: float = 2.0
    stab_grid_bits: int = 6
    stab_segments: tuple = (5, 10, 20, 40, 80)
    stab_segment_stiffness: tuple = (1e-5, 1e-3, 1e-1)
    stab_mass_ratios: tuple = (1.0, 0.3, 0.1, 0.03, 0.01)
    stab_mass_stiffness: float = 1e-3
    stab_side_duration: float = 1.0
    stab_joint_damping: float = 1.0e-10
    stab_hair_damping: float = 2.0e-7
    stab_hair_integrators: tuple = ("semi_implicit", "implicit_joints")
    # timings wait for other programs to leave the cores (QuietGate), within this budget per suite
    quiet_gate: bool = True
    quiet_budget_s: float = 20.0
    quiet_max_wait_s: float = 5.0
    # scaling
    scale_strands: tuple = (32, 128, 512, 2228)
    # five segment counts: a fit through three noisy points (10-15 % between blocks here) swung by 0.1 or more
    scale_segments: tuple = (8, 12, 16, 24, 31)
    scale_budget_s: float = 0.7
    scale_passes: int = 3
    scale_blocks: int = 7
    dense_counts: tuple = (10_000, 100_000)
    stages: tuple | None = None  # names of the stage hooks to call (None: all of scaling.STAGE_HOOKS)

    @classmethod
    def full(cls, device: str = "cpu") -> BenchConfig:
        return cls(device=device)

    @classmethod
    def quick_preset(cls, device: str = "cpu") -> BenchConfig:
        """About a minute on a 2-core machine: small sizes, Newton skipped, short time boxes."""
        return cls(
            quick=True,
            device=device,
            dyn_configs=[(20, 10), (20, 20)],
            dyn_peers=("pinocchio", "pinocchio_parallel", "mujoco_euler", "mujoco_rollout_euler_t0",
                       "mujoco_rollout_euler_threads"),
            block_steps=20,
            ours_budget_s=0.5,
            peer_budget_s=1.0,
            peer_timeout_s=60.0,
            acc_ref_dt=1e-4,
            acc_duration=0.5,
            acc_dts=(1e-3, 1e-4),
            acc_peer_dts={"pinocchio_euler": (1e-3, 1e-4), "mujoco_euler": (1e-3,), "mujoco_rk4": (1e-3,),
                          "mujoco_discrete": (1e-3,)},
            acc_cost_strands=20,
            conv_segments=(5, 10, 20),
            stab_stiffness=(1e-5, 1e-3, 1e-1),
            stab_integrators=("semi_implicit", "implicit_joints"),
            stab_mujoco=("implicitfast", "discrete"),
            stab_mujoco_stiffness=(1e-5, 1e-1),
            stab_newton_stiffness=(1e-3,),
            stab_duration=0.5,
            stab_grid_bits=3,
            stab_segments=(5, 20),
            stab_segment_stiffness=(1e-3,),
            stab_mass_ratios=(1.0, 0.1),
            stab_side_duration=0.25,
            stab_hair_integrators=("semi_implicit",),
            scale_strands=(16, 64),
            scale_segments=(8, 16),
            scale_budget_s=0.2,
            scale_passes=1,
            scale_blocks=3,
            dense_counts=(1000,),
            quiet_budget_s=5.0,
            quiet_max_wait_s=2.0,
        )


def ratboy_paths():
    """The shared TressFX Ratboy groom and body beside the source checkout, as ``(groom, body)`` paths (they may be
    absent)."""
    from pathlib import Path

    base = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tressfx_ratboy"
    return base / "Ratboy_mohawk.tfx", base / "Ratboy_body.tfxmesh"


def ratboy_assets(groom_path=None, body_path=None):
    """``(groom, body, None)`` paths of the Ratboy assets (the given ones, else ``ratboy_paths``), or
    ``(groom, body, skipped)`` with the ``{"status": "skipped", "message"}`` a benchmark returns when one is
    missing."""
    from pathlib import Path

    default_groom, default_body = ratboy_paths()
    groom, body = Path(groom_path or default_groom), Path(body_path or default_body)
    missing = [str(p) for p in (groom, body) if not p.is_file()]
    if missing:
        return groom, body, {"status": "skipped",
                             "message": f"needs the TressFX Ratboy assets: {', '.join(missing)} missing"}
    return groom, body, None


def ratboy_mohawk_scene(groom_path, body_path, device, max_strands: int, overrides=()):
    """The shipped ``ratboy_mohawk`` scene on the asset files of :func:`ratboy_assets`, on ``device``, with
    ``groom.max_strands`` (0: every guide) and more ``key=value`` overrides."""
    from pathlib import Path

    from hairwarp.scene import Scene

    return Scene.load(Path(Scene.default_path()).parent / "ratboy_mohawk.toml", [
        f"groom.file='{groom_path}'", f"head.file='{body_path}'", f"groom.max_strands={int(max_strands)}",
        f"sim.device='{device}'", *overrides])


def timed_samples(fn, device, repeats: int) -> list[float]:
    """Wall times [s] of ``repeats`` calls of ``fn`` behind one untimed call (which brings its arrays back into the
    caches), with ``wp.synchronize_device`` around each."""
    import warp as wp

    fn()
    samples = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        samples.append(time.perf_counter() - t0)
    return samples


def interleaved_medians(calls: dict, device, repeats: int) -> dict:
    """Median wall time [s] of each call (name -> function), timed in turn ``repeats`` times after one warm-up round,
    with ``wp.synchronize_device`` around each, so a load change on a shared machine hits every figure alike."""
    import warp as wp

    samples = {name: [] for name in calls}
    for r in range(repeats + 1):
        for name, fn in calls.items():
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            fn()
            wp.synchronize_device(device)
            if r:
                samples[name].append(time.perf_counter() - t0)
    return {name: float(np.median(v)) for name, v in samples.items()}
