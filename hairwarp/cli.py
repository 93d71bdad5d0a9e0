"""The ``hairwarp`` command: run scenes, inspect files, benchmark, preview caches.

::

    hairwarp run [SCENE] [-o OUT.usdc] [--frames N] [--device D] [--threads N] [--up-axis Y|Z] [--units M]
                 [--start-frame N] [-s KEY=VALUE ...]
    hairwarp info FILE              # a scene (.toml), a groom (.tfx, .hair, .usd*) or a cache (.usd*)
    hairwarp schema [SECTION]       # every scene key: type, default, range, unit, meaning
    hairwarp bench [SUITE] [--quick] [--device D] [--threads N] [--out DIR] [--format human|json]
    hairwarp preview CACHE [-o PICTURE] [--frames N] [--gif] [--guides]
    hairwarp wedge [SCENE] -w KEY=V1,V2,... [-w ...] [--grid | --zip] [-o DIR] [--scheduler ADDRESS | --workers N]
    hairwarp batch SCENE... | @LIST.txt [-o DIR] [--scheduler ADDRESS | --workers N]

Exit codes: 0 success; 1 a part of hairwarp this installation lacks (for ``wedge`` and ``batch``: Dask);
2 bad input (usage, scene, groom or cache errors, a missing file, an output that cannot be written, a missing
device, not enough memory or disk for the run, another run on the same output; for ``wedge`` every variant is
checked before any runs), with one message on stderr and no traceback; 3 the simulation stopped on a fault (the
message names the frame, the stage and the parameter) or writing the cache or the picture failed (disk full, I/O
error; a run whose preview failed says that its cache is complete); for
``wedge`` and ``batch``: some runs faulted, failed or were lost, the others finished, the summary says which;
128 + N a signal N stopped the run (130 SIGINT, 143 SIGTERM, 129 SIGHUP) after its last complete frame; 141
(128 + SIGPIPE) the reader of the output went away (``hairwarp schema | head``), quietly, as other commands do.
Set ``HAIRWARP_TRACEBACK=1`` to get the traceback of an error instead of the one-line message.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import warnings
from pathlib import Path

__all__ = ["build_parser", "main"]

EXIT_OK = 0
EXIT_MISSING_PART = 1
EXIT_BAD_INPUT = 2
EXIT_FAULT = 3
#: The reader of the standard output went away (``hairwarp schema | head -3``): 128 + SIGPIPE, what a command the
#: signal ends reports, so the command is quiet and a ``set -o pipefail`` script sees the usual cut-short status.
EXIT_BROKEN_PIPE = 128 + 13  # SIGPIPE is 13 on every POSIX system (Windows has no signal.SIGPIPE to read it from)

#: The signals that stop a run besides SIGINT (which Python turns into KeyboardInterrupt), where the system has them.
_STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))

#: Frames on the contact sheet of ``hairwarp preview`` when --frames is not given.
_SHEET_FRAMES = 4

_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
_GROOM_SUFFIXES = (".tfx", ".hair")


# ----------------------------------------------------------------------------------------------
# commands


def _cmd_run(args) -> int:
    from hairwarp.scene import Scene

    path = Path(args.scene) if args.scene else Scene.default_path()
    overrides = _with_options(args.set, [
        ("--frames", "sim.frames", args.frames),
        ("--device", "sim.device", None if args.device is None else repr(args.device)),
        ("--up-axis", "output.up_axis", None if args.up_axis is None else repr(args.up_axis)),
        ("--meters-per-unit", "output.meters_per_unit",
         None if args.meters_per_unit is None else repr(args.meters_per_unit)),
        ("--start-frame", "output.start_frame", args.start_frame),
        ("--threads", "sim.threads", args.threads),
    ])
    scene = Scene.load(path, overrides=overrides)
    for key, why in scene.unread_keys(o.split("=", 1)[0].strip() for o in args.set or ()):
        warnings.warn(f"-s {key}: {why}", stacklevel=1)
    out = Path(args.output) if args.output else Path("out") / f"{scene.name}.usdc"

    from hairwarp.runner import simulate

    result = simulate(scene, out, frames=args.frames, device=args.device, progress=True, resume=args.resume,
                      profile=args.profile)
    print(f"cache    {Path(result.cache_path).absolute()}")  # as the set-up line names it
    preview = getattr(result, "preview_path", None)
    if preview:
        print(f"preview  {Path(preview).absolute()}")
    simulated = result.frames - result.resumed_frames
    resumed = ""
    if result.resumed_frames:
        resumed = f" after the {_counted(result.resumed_frames, 'frame')} of the stopped run"
    rate = f" ({result.seconds_per_frame:.3g} s a frame)" if simulated else ""  # none: no time a frame to give
    extras = "the set-up and the preview" if preview else "the set-up"
    print(f"{_counted(simulated, 'frame')} simulated{resumed} in {result.frame_seconds:.2f} s{rate}; "
          f"{result.seconds:.2f} s in all, with {extras}")
    for note in result.notes:  # what the run noticed: buffers that overflowed, frames taken again, a held groom
        print(f"note     {note}")
    if result.stage_seconds is not None and simulated:
        print("\n".join(_stage_table(result.stage_seconds, result.frame_seconds, simulated)))
    return EXIT_OK


#: The stages ``hairwarp run --profile`` lists, in a step's order (``Solver.profile_stages``), and what each holds.
STAGES = (
    ("dynamics", "the free step and drag"),
    ("body collision", "detection and push-out"),
    ("links", "their forces"),
    ("hair contacts: detection", "pairs found"),
    ("hair contacts: forces", "on the pairs found"),
    ("response", "solved after the free step"),
    ("output", "curves, checkpoints, cache"),
)


def _stage_table(stages: dict, frame_seconds: float, frames: int) -> list[str]:
    """``hairwarp run --profile``'s table: each stage's time a frame and share of the frames' time, the rest (the
    host between the stages) last."""
    rows = [(name, what, stages[name]) for name, what in STAGES if name in stages]
    rows.append(("other", "the host between stages", max(frame_seconds - sum(t for _, _, t in rows), 0.0)))
    lines = ["time by stage (--profile: each stage synchronised and timed apart, a little slower than a plain run)"]
    for name, what, seconds in rows:
        lines.append(f"  {name:<25} {seconds / frames * 1e3:9.2f} ms a frame {100.0 * seconds / frame_seconds:5.1f} %"
                     f"   {what}")
    return lines


def _counted(count: int, noun: str) -> str:
    """``count`` and ``noun``, in the plural unless it is one ("1 frame", "0 frames", "24 frames")."""
    return f"{count} {noun}" if count == 1 else f"{count} {noun}s"


def _cmd_schema(args) -> int:
    from hairwarp.scene import schema_doc

    text = schema_doc()
    if args.section:
        keep, show = [], False
        for line in text.splitlines():
            if line.startswith("["):
                name = line[1:].lstrip("[").split("]")[0]
                show = name == args.section or name.startswith(args.section + ".")
            if show:
                keep.append(line)
        if not keep:
            sections = sorted({ln[1:].lstrip("[").split("]")[0].split(".")[0] for ln in text.splitlines()
                               if ln.startswith("[")})
            print(f"hairwarp schema: no section {args.section!r}; sections: {', '.join(sections)}", file=sys.stderr)
            return EXIT_BAD_INPUT
        text = "\n".join(keep)
    print(text)
    return EXIT_OK


def _no_such_file(path: Path) -> FileNotFoundError:
    """The error for a file that is not there, naming the cache a stopped or killed run left in ``<stem>.partial``
    beside it (``hairwarp.io.cache_folder``), which holds every frame it completed."""
    partial = path.with_name(path.stem + ".partial") / path.name
    if partial.is_file():
        return FileNotFoundError(f"{path.resolve()}: no such file; the run that writes it has not finished (it runs, "
                                 f"or it stopped) and keeps its complete frames in {partial.resolve()}: read them "
                                 f"there, or finish a stopped run with hairwarp run --resume")
    return FileNotFoundError(f"{path.resolve()}: no such file")


def _cmd_info(args) -> int:
    path = Path(args.file)
    if not path.exists():
        raise _no_such_file(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; name a scene (.toml), a groom or a cache in it")
    suffix = path.suffix.lower()
    if args.set and suffix != ".toml":
        raise ValueError(f"{path}: -s overrides apply to a scene (.toml), not to {suffix or 'this file'}")
    if suffix == ".toml":
        from hairwarp.runner import Simulation
        from hairwarp.scene import Scene

        scene = Scene.load(path, args.set or ())
        print(scene.summary())
        Simulation.check_colliders(scene)  # their files and prims, as a run reads them
    elif suffix in _GROOM_SUFFIXES:
        print(_groom_summary(path))
    elif suffix in _USD_SUFFIXES:
        from hairwarp.io.usd_inspect import describe

        animated, has_curves = _usd_kind(path)
        # A static stage with curves is a groom: read it first, so a bad strand is the one line printed.
        summary = _groom_summary(path) if has_curves and not animated else None
        text = describe(path)
        print(text if isinstance(text, str) else "\n".join(f"{k}: {v}" for k, v in dict(text).items()))
        if summary:
            print(summary)
    else:
        raise ValueError(f"{path}: cannot tell what {suffix or 'a file without suffix'} is; "
                         f"expected .toml, {', '.join(_GROOM_SUFFIXES + _USD_SUFFIXES)}")
    return EXIT_OK


def _groom_summary(path: Path) -> str:
    import warnings

    import numpy as np

    from hairwarp.groom import Groom

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the dropped strands are a line of the summary below
        groom = Groom.load(path)
    counts = np.array([len(s) for s in groom.strands])
    lengths = groom.lengths()
    lo, hi = groom.bounds()
    fmt = "[{:.4g}, {:.4g}, {:.4g}]".format
    lines = [
        f"groom    {path}",
        f"strands  {groom.strand_count}",
        f"vertices {int(counts.sum())} (per strand {counts.min()} .. {counts.max()}, mean {counts.mean():.1f})",
        f"length   {lengths.min():.4g} .. {lengths.max():.4g} m, mean {lengths.mean():.4g} m, "
        f"total {lengths.sum():.4g} m",
        f"bounds   {fmt(*lo)} .. {fmt(*hi)} m (Z up), size {fmt(*(hi - lo))} m",
    ]
    if groom.grid_shape is not None:
        lines.append(f"grid     {groom.grid_shape[0]} x {groom.grid_shape[1]} roots")
    if groom.dropped:
        from hairwarp.groom import _index_list

        lines.append(f"dropped  {len(groom.dropped)} of {groom.strand_count + len(groom.dropped)} strands shorter "
                     f"than {groom.min_length:g} m ({_index_list(groom.dropped)}), not simulated")
    return "\n".join(lines)


def _usd_kind(path: Path) -> tuple[bool, bool]:
    """(animated: a point-based prim has time samples, has_curves: the stage holds a BasisCurves prim)."""
    from pxr import UsdGeom

    from hairwarp.io.usd_common import _open_stage

    stage = _open_stage(path)
    animated = has_curves = False
    for prim in stage.Traverse():
        has_curves = has_curves or prim.IsA(UsdGeom.BasisCurves)
        if prim.IsA(UsdGeom.PointBased) and UsdGeom.PointBased(prim).GetPointsAttr().GetNumTimeSamples() > 1:
            animated = True
    return animated, has_curves


def _cmd_bench(args) -> int:
    from hairwarp.bench import main as bench_main

    return int(bench_main(args) or 0)


def _cmd_preview(args) -> int:
    path = Path(args.cache)
    if not path.exists():
        raise _no_such_file(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; name the cache file in it")
    from hairwarp.preview import MAX_SHEET_FRAMES, cache_frames, preview_cache

    frames = _SHEET_FRAMES if args.frames is None else args.frames
    if args.frames is not None:  # what was asked and will not be shown is said, not dropped silently
        available = len(cache_frames(path))
        if args.gif:
            _note(f"--frames is for the contact sheet; the GIF shows every frame of the cache ({available})")
        elif min(args.frames, available) > MAX_SHEET_FRAMES:
            _note(f"a contact sheet shows at most {MAX_SHEET_FRAMES} frames: {MAX_SHEET_FRAMES} of the cache's "
                  f"{available}, evenly spaced (--gif shows every frame)")
        elif args.frames > available:
            _note(f"the cache has {_counted(available, 'frame')}, fewer than --frames {args.frames}: the sheet "
                  f"shows {'it' if available == 1 else f'all {available}'}")
    out = preview_cache(path, args.output, frames=frames, gif=args.gif, progress=True, guides=args.guides)
    print(f"preview  {out}")
    return EXIT_OK


def _dask_missing(command: str) -> bool:
    """Tell the user how to install Dask when it is missing (``wedge`` and ``batch`` run on it)."""
    try:
        import distributed  # noqa: F401
    except ModuleNotFoundError:
        from hairwarp.farm import INSTALL_HINT

        _error(f"'{command}' runs on Dask, which this installation does not have: {INSTALL_HINT}")
        return True
    return False


def _with_options(sets, options) -> list[str]:
    """The ``-s`` overrides ``sets``, then one for each option given, ``(option, key, value or None)``. A key given
    both ways is refused: the option's value won, and a bad ``-s`` value for it went unchecked."""
    overrides = list(sets or [])
    given = {o.split("=", 1)[0].strip(): o for o in overrides}
    for option, key, value in options:
        if value is None:
            continue
        if key in given:
            raise ValueError(f"{key} is set twice, by -s {given[key]} and by {option}; give it once")
        overrides.append(f"{key}={value}")
    return overrides


def _common_overrides(args) -> list[str]:
    return _with_options(args.set, [("--frames", "sim.frames", args.frames)])


def _cmd_wedge(args) -> int:
    if _dask_missing("wedge"):
        return EXIT_MISSING_PART
    from hairwarp import farm
    from hairwarp.scene import Scene

    path = Path(args.scene) if args.scene else Scene.default_path()
    params: dict[str, list[str]] = {}
    for key, values in args.wedge:
        if key in params:
            raise ValueError(f"-w {key} is given twice; list all its values in one -w {key}=V1,V2,...")
        params[key] = values
    overrides = _common_overrides(args)
    fixed = {o.split("=", 1)[0].strip(): o for o in overrides}
    for key in params:
        if key in fixed:  # the wedge's value would silently win over the fixed one in every run
            given = "--frames" if fixed[key] == f"sim.frames={args.frames}" else f"-s {fixed[key]}"
            raise ValueError(f"{key} is both wedged (-w {key}=...) and fixed ({given}); give it one way")
    base = Scene.load(path, overrides=overrides)
    unread = [(key, why) for key, why in base.unread_keys(params) if key.split(".", 1)[0] + ".enabled" not in params
              and not (key.startswith("dense.") and {"dense.count", "dense.density"} & params.keys())]
    if unread:  # every variant would run the same
        raise ValueError(f"-w {unread[0][0]}: {unread[0][1]}")
    out = Path(args.output) if args.output else Path("out") / f"wedge_{base.name}"
    tasks = farm.wedge_tasks(path, params, out, mode="zip" if args.zip else "grid", overrides=overrides)
    farm.make_output_folder(out)  # once the variants are checked: a bad key leaves no folder behind
    print(f"wedge    {_counted(len(tasks), 'variant')} of {path} into {out}", file=sys.stderr)
    return _run_farm(args, farm, tasks, out, shared_framing=True)


def _cmd_batch(args) -> int:
    if _dask_missing("batch"):
        return EXIT_MISSING_PART
    from hairwarp import farm

    out = Path(args.output) if args.output else Path("out") / "batch"
    tasks = farm.batch_tasks(args.scenes, out, overrides=_common_overrides(args))
    farm.make_output_folder(out)
    print(f"batch    {_counted(len(tasks), 'shot')} into {out}", file=sys.stderr)
    return _run_farm(args, farm, tasks, out, shared_framing=False)


def _run_farm(args, farm, tasks, out: Path, shared_framing: bool) -> int:
    import time

    t0 = time.perf_counter()
    try:
        records = farm.run_tasks(tasks, out, scheduler=args.scheduler, workers=args.workers, retries=args.retries,
                                 progress=True, sheet=not args.no_sheet, shared_framing=shared_framing)
    except KeyboardInterrupt:
        _error(f"interrupted: unfinished runs cancelled; a rerun reuses the finished ones in {out}")
        return 130
    counts: dict[str, int] = {}
    for r in records:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    for r in records:
        if r["status"] != farm.STATUS_OK:
            print(f"{r['status']:<8} {r['name']}: {r['message']}")
    print(f"summary  {out / 'summary.csv'}  {out / 'summary.md'}  {out / 'summary.json'}")
    if (out / "sheet.png").is_file() and not args.no_sheet:
        print(f"sheet    {out / 'sheet.png'}")
    reused = sum(1 for r in records if r.get("skipped"))
    print(f"{len(records)} runs: " + ", ".join(f"{n} {k}" for k, n in counts.items())
          + (f" ({reused} complete before, not rerun)" if reused else "") + f" in {time.perf_counter() - t0:.1f} s")
    return EXIT_OK if counts.get(farm.STATUS_OK, 0) == len(records) else EXIT_FAULT


# ----------------------------------------------------------------------------------------------
# parser


def _nonnegative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def _thread_count(text: str) -> int:
    from hairwarp.executor import MAX_THREADS

    value = _nonnegative_int(text)
    if value > MAX_THREADS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_THREADS} threads, got {value}")
    return value


def _path(text: str) -> str:
    """An output path: not empty (an empty ``-o`` fell back to the default path without a word)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty one")
    return text


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _override(text: str) -> str:
    if "=" not in text or not text.split("=", 1)[0].strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE such as sim.frames=10, got {text!r}")
    return text


def _wedge_param(text: str) -> tuple[str, list[str]]:
    from hairwarp.farm import split_values

    key, sep, values = text.partition("=")
    if not sep or not key.strip() or not values.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=V1,V2,... such as strands.bend_stiffness=1e-4,1e-3, "
                                         f"got {text!r}")
    return key.strip(), split_values(values)


def _farm_options(p) -> None:
    p.add_argument("-o", "--output", type=_path, metavar="DIR",
                   help="output folder (one subfolder per run, the summaries and the contact sheet)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="a running Dask scheduler, e.g. tcp://host:8786 (dask-jobqueue, dask-kubernetes); "
                            "default: a local cluster")
    where.add_argument("--workers", type=_positive_int, metavar="N",
                       help="worker processes of the local cluster (default: one per core this process may use)")
    p.add_argument("--frames", type=_positive_int, metavar="N", help="output frames of every run (sim.frames)")
    p.add_argument("-s", "--set", action="append", type=_override, metavar="KEY=VALUE",
                   help="override a scene key in every run (repeatable)")
    p.add_argument("--retries", type=_nonnegative_int, default=2, metavar="N",
                   help="reruns of a run after an error other than a simulation fault (default 2)")
    p.add_argument("--no-sheet", action="store_true", help="do not draw the contact sheet")


def _version() -> str:
    from hairwarp import __version__

    return f"hairwarp {__version__}"


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose errors are one line, as every other error of the command (argparse prints its usage
    block first): ``hairwarp run: --threads: must be ... (hairwarp run --help)``, exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {message} ({self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``hairwarp`` command."""
    parser = _Parser(
        prog="hairwarp",
        description="Hair simulation on NVIDIA Warp: articulated guide strands written to USD caches.",
        epilog="Run 'hairwarp COMMAND --help' for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)

    p = sub.add_parser("run", help="simulate a scene and write a USD cache (and a preview)",
                       description="Simulate a scene and write a USD cache and a preview picture.")
    p.add_argument("scene", nargs="?", metavar="SCENE",
                   help="scene file (.toml); default: the bundled long_hair scene")
    p.add_argument("-o", "--output", type=_path, metavar="OUT.usdc",
                   help="cache to write; default: out/<scene name>.usdc")
    p.add_argument("--frames", type=_positive_int, metavar="N", help="output frames (overrides sim.frames)")
    p.add_argument("--device", metavar="D", help="Warp device: cpu, cuda, cuda:N (overrides sim.device)")
    p.add_argument("--up-axis", choices=("Y", "Z"), help="up axis of the cache (overrides output.up_axis)")
    p.add_argument("--meters-per-unit", "--units", type=float, metavar="M",
                   help="unit of the cache in metres, e.g. 0.01 for centimetres (overrides output.meters_per_unit)")
    p.add_argument("--start-frame", type=_nonnegative_int, metavar="N",
                   help="time code of the first frame (overrides output.start_frame)")
    p.add_argument("--threads", type=_thread_count, metavar="N",
                   help="CPU threads (overrides sim.threads; 0: every core this process may use)")
    p.add_argument("--profile", action="store_true",
                   help="time each stage of the frames (dynamics, collision, links, hair contacts, response, output) "
                        "and print the table at the end")
    p.add_argument("--resume", action="store_true",
                   help="continue the run a stop or a fault left beside the output, after its last complete frame")
    p.add_argument("-s", "--set", action="append", type=_override, metavar="KEY=VALUE",
                   help="override a scene key, value in TOML syntax, e.g. -s sim.substeps=4 "
                        "-s 'head.motion.kind=\"nod\"' (repeatable)")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("schema", help="print every scene key: type, default, range, unit and meaning",
                       description="The scene reference: every key of a scene file, section by section.")
    p.add_argument("section", nargs="?", metavar="SECTION", help="only this section, e.g. output or head.motion")
    p.set_defaults(func=_cmd_schema)

    p = sub.add_parser("info", help="describe a scene, a groom or a cache",
                       description="Describe a scene (.toml), a groom (.tfx, .hair, .usd*) or a cache (.usd*).")
    p.add_argument("file", metavar="FILE")
    p.add_argument("-s", "--set", action="append", type=_override, metavar="KEY=VALUE",
                   help="a scene: override a key as hairwarp run does, to check it before a run (repeatable)")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("bench", help="time and measure the accuracy of the solver",
                       description="Benchmarks: speed and accuracy of the solver.")
    from hairwarp.bench import EXTRA_SUITES, SUITES

    p.add_argument("suite", nargs="?", metavar="SUITE",
                   help=f"benchmark suite: {', '.join(SUITES)} ('all', the default, runs these), or one of "
                        f"{', '.join(EXTRA_SUITES)}")
    p.add_argument("--quick", action="store_true", help="small sizes, for a smoke check")
    p.add_argument("--device", metavar="D", help="Warp device")
    p.add_argument("--threads", type=_thread_count, metavar="N",
                   help="CPU threads of the timed runs (default: every core this process may use; the threads "
                        "suite times 1 against N)")
    p.add_argument("--out", metavar="DIR", help="folder for results and charts")
    p.add_argument("--format", choices=("human", "json"), default="human", help="output format")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("preview", help="render frames of a cache to a PNG (or a GIF)",
                       description="Render frames of a USD cache as a contact sheet PNG or an animated GIF.")
    p.add_argument("cache", metavar="CACHE")
    p.add_argument("-o", "--output", type=_path, metavar="PICTURE",
                   help="picture to write: a .png (a .gif with --gif; the suffix names the format written, another "
                        "is refused); default: beside the cache")
    p.add_argument("--frames", type=_positive_int, metavar="N",
                   help=f"frames on the sheet, evenly spaced, the first and the last included (default "
                        f"{_SHEET_FRAMES}; every frame of a cache that has fewer)")
    p.add_argument("--gif", action="store_true",
                   help="write an animated GIF of every frame instead (--frames is then not used)")
    p.add_argument("--guides", action="store_true",
                   help="draw the guide strands too, in orange (default: the dense hair alone when the cache has it, "
                        "as the run's preview)")
    p.set_defaults(func=_cmd_preview)

    p = sub.add_parser("wedge", help="run variants of a scene on Dask (one run per combination of values)",
                       description="Run variants of a scene, one Dask task each, on a local cluster or a Dask "
                                   "scheduler; write each run's cache, preview and stats, a summary and a contact "
                                   "sheet. A rerun skips the runs already complete.")
    p.add_argument("scene", nargs="?", metavar="SCENE", help="scene file (.toml); default: the bundled long_hair")
    p.add_argument("-w", "--wedge", action="append", type=_wedge_param, required=True, metavar="KEY=V1,V2,...",
                   help="a key and its values, in TOML syntax (repeatable), e.g. -w strands.bend_stiffness=1e-4,1e-3")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--grid", action="store_true", help="every combination of the values (default)")
    mode.add_argument("--zip", action="store_true", help="the i-th value of every key together (equal lengths)")
    _farm_options(p)
    p.set_defaults(func=_cmd_wedge)

    p = sub.add_parser("batch", help="run several scenes (shots) on Dask",
                       description="Run several scenes, one Dask task each, like 'wedge' does for variants.")
    p.add_argument("scenes", nargs="+", metavar="SCENE", help="scene files, or @LIST.txt (one scene a line)")
    _farm_options(p)
    p.set_defaults(func=_cmd_batch)
    return parser


# ----------------------------------------------------------------------------------------------
# entry point


def _error(message: str) -> None:
    if "pxr" in message or "\n" in message:  # usd-core's text can reach any message that quotes an error
        from hairwarp.io.usd_common import clean_usd_text

        message = clean_usd_text(message)
    print(f"hairwarp: {message}", file=sys.stderr)


def _note(message: str) -> None:
    """One line on stderr about an option that does less than asked; the command goes on."""
    print(f"hairwarp: note: {message}", file=sys.stderr)


def _is_usd_error(exc: BaseException) -> bool:
    tf = sys.modules.get("pxr.Tf")
    return tf is not None and isinstance(exc, tf.ErrorException)


#: What Warp's native library prints on a machine without the CUDA driver, on every start (not news on a CPU).
_NO_CUDA_DRIVER = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def _init_warp_quietly(wp) -> None:
    """``wp.init()`` with the native library's standard error caught, and given back without the missing-driver
    warning (written by C code, past Python's ``sys.stderr`` and Warp's own quiet settings)."""
    import tempfile

    try:
        saved = os.dup(2)
    except OSError:
        wp.init()
        return
    with tempfile.TemporaryFile() as caught:
        sys.stderr.flush()
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        text = caught.read().decode("utf-8", "replace")
    kept = [line for line in text.splitlines(keepends=True) if not line.startswith(_NO_CUDA_DRIVER)]
    if kept:
        sys.stderr.write("".join(kept))


def main(argv=None) -> int:
    """Run the ``hairwarp`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit code.

    Usage errors exit through argparse (``SystemExit(2)``); ``--help`` and ``--version`` exit 0.
    """
    args = build_parser().parse_args(argv)
    # a warning is one line of its own, as the errors are (not the source line that raised it); for this command only
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        try:
            with _stops_before_the_run(args.command == "run"):
                code = _main(args)
            sys.stdout.flush()  # a reader gone shows here, not in the interpreter's last flush (its own traceback)
            return code
        except _StoppedBeforeTheRun as stop:
            _error(f"stopped by {signal.Signals(stop.signum).name} before the run began; nothing was written")
            return 128 + stop.signum
        except BrokenPipeError:
            _stdout_to_devnull()
            return EXIT_BROKEN_PIPE


def _stdout_to_devnull() -> None:
    """Point standard output at /dev/null, so that what is left in its buffer is dropped at exit instead of failing
    once more on the closed pipe (Python's documented way, "Note on SIGPIPE" in the ``signal`` module)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by an object without a file (a test's capture)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


class _StoppedBeforeTheRun(BaseException):
    """SIGTERM or SIGHUP while ``run`` starts (Warp loads, the scene is checked), before the run takes the signals
    over. A BaseException, as KeyboardInterrupt, so that no ``except Exception`` on the way swallows it."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def _stops_before_the_run(active: bool):
    """While ``active``: SIGTERM and SIGHUP end the command at once with one line and exit code 128 + signal, as
    SIGINT does, instead of the default's silent end. :func:`hairwarp.runner.simulate` takes them over from its lock
    on (it stops after the frame in flight, releases the lock and says what it kept) and gives them back after."""
    import threading

    if not active or threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, _frame):
        raise _StoppedBeforeTheRun(signum)

    previous = {sig: signal.signal(sig, stop) for sig in _STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"hairwarp: warning: {message}", file=sys.stderr if file is None else file)


def _main(args) -> int:
    try:  # Warp's banner, its module-load lines and the CUDA-driver warning of a CPU machine: not news on every run
        import warp as wp

        wp.config.quiet = True  # Warp before 1.19
        if hasattr(wp, "LOG_ERROR"):
            wp.config.log_level = wp.LOG_ERROR
        _init_warp_quietly(wp)
    except ImportError:
        pass
    if os.environ.get("HAIRWARP_TRACEBACK"):
        return args.func(args)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as exc:
        _error(str(exc))
        return EXIT_BAD_INPUT
    except ModuleNotFoundError as exc:
        if not (exc.name or "").startswith("hairwarp"):
            raise
        _error(f"'{args.command}' needs {exc.name}, which this installation does not have")
        return EXIT_MISSING_PART
    except RuntimeError as exc:
        solver = sys.modules.get("hairwarp.solver")
        folder = sys.modules.get("hairwarp.io.cache_folder")
        if folder is not None and isinstance(exc, folder.CacheWriteError):
            _error(f"writing the cache failed: {exc}")
            return EXIT_FAULT
        preview = sys.modules.get("hairwarp.preview")
        if preview is not None and isinstance(exc, preview.PreviewWriteError):
            _error(str(exc))
            return EXIT_FAULT
        if _is_usd_error(exc):  # a file usd-core could not read or write, past hairwarp's own checks
            from hairwarp.io.usd_common import usd_error_text

            _error(f"USD: {usd_error_text(exc)}")
            return EXIT_BAD_INPUT
        if solver is None or not isinstance(exc, getattr(solver, "SimulationFault", ())):
            raise
        _error(f"simulation stopped: {exc}")
        return EXIT_FAULT
    except KeyboardInterrupt:
        _error("interrupted; the frame in flight was dropped")
        return 128 + 2
    except Exception as exc:
        runner = sys.modules.get("hairwarp.runner")
        if runner is None or not isinstance(exc, runner.RunStopped):
            raise
        _error(str(exc))
        return 128 + exc.signum
