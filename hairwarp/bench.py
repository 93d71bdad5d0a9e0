"""``hairwarp bench``: speed, accuracy, stability and scaling of the strand solver, with the peers.

Usage::

    hairwarp bench [SUITE] [--quick] [--device D] [--out DIR] [--format human|json]
    python -m hairwarp.bench [SUITE] [--quick] [--device D] [--out DIR] [--format human|json]

SUITE is ``dynamics``, ``accuracy``, ``stability``, ``scaling``, ``budget`` or ``all`` (the default), or a
suite run only when named: ``collision``, ``interactions``, ``dense``, ``wedge`` or ``robustness``
(``EXTRA_SUITES``). A run writes ``benchmarks.json`` (every figure and the machine it ran on), PNG charts and the report
``benchmarks.md`` into the output folder: ``docs/`` of the source checkout for a full run,
``out/bench-quick/`` for ``--quick`` (a smoke run never overwrites the committed report).
Running one suite keeps the other suites' figures already in the folder's JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from hairwarp.benchmarks import SUITES

# Suites other modules provide, run only when named: name -> (module, function(config, out, log) -> dict).
EXTRA_SUITES = {
    "collision": ("hairwarp.benchmarks.collision", "suite_collision"),
    "interactions": ("hairwarp.benchmarks.interactions", "suite_interactions"),
    "dense": ("hairwarp.benchmarks.dense", "suite_dense"),
    "wedge": ("hairwarp.benchmarks.wedge", "suite_wedge"),
    "robustness": ("hairwarp.benchmarks.robustness", "suite_robustness"),
    "threads": ("hairwarp.benchmarks.threads", "suite_threads"),
}
JSON_NAME = "benchmarks.json"
REPORT_NAME = "benchmarks.md"
SCHEMA = 1


def _log_to_stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def default_out(quick: bool) -> Path:
    """``<checkout>/docs`` for a full run from a source checkout, else ``out/bench``; quick: ``out/bench-quick``."""
    if quick:
        return Path("out") / "bench-quick"
    root = Path(__file__).resolve().parents[1]
    if (root / "pyproject.toml").is_file() and (root / "docs").is_dir():
        return root / "docs"
    return Path("out") / "bench"


def run_suites(suites, config, out: Path, log=_log_to_stderr) -> dict:
    """Run ``suites`` with ``config`` (a :class:`hairwarp.benchmarks.common.BenchConfig`); write the JSON,
    the charts and the report into ``out``; return the results (what the JSON holds)."""
    import warp as wp

    from hairwarp.benchmarks import common, report

    wp.config.quiet = True
    wp.init()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / JSON_NAME
    results = {"schema": SCHEMA, "suites": {}}
    old_machine = None
    if path.is_file():
        try:
            old = json.loads(path.read_text())
            if old.get("schema") == SCHEMA:
                results["suites"] = old.get("suites", {})
                old_machine = old.get("machine")
        except (OSError, ValueError):
            pass
    machine = common.machine_info()
    # The report's header describes the machine of the last run of every main suite; a run of some suites (each
    # names its own machine in its section's footer) leaves it as it was.
    keep_header = old_machine is not None and not set(SUITES) <= set(suites)
    results["machine"] = old_machine if keep_header else machine
    t_all = time.perf_counter()
    done = 0
    try:
        for name in suites:
            log(f"== suite {name} ==")
            t0 = time.perf_counter()
            common.GATE.enabled = config.quiet_gate
            common.GATE.budget_s = config.quiet_budget_s
            common.GATE.max_wait_s = config.quiet_max_wait_s
            common.GATE.reset()
            data = _suite(name, config, out, log)
            data["quiet_gate"] = common.GATE.summary()
            data["wall_s"] = round(time.perf_counter() - t0, 1)
            data["quick"] = config.quick
            data["machine"] = {**machine, "load_average_end": common.load_average()}
            results["suites"][name] = data
            done += 1
            log(f"== suite {name}: {data['wall_s']} s ==")
            path.write_text(json.dumps(results, indent=1, default=json_default))
    except BaseException:
        if done:  # the suites that finished keep their report and charts
            report.write_report(results, out)
            log(f"wrote the report of the {done} suite{'s' if done > 1 else ''} that finished to {out}")
        raise
    results["wall_s"] = round(time.perf_counter() - t_all, 1)
    if not keep_header:
        results["machine"]["load_average_end"] = common.load_average()
    path.write_text(json.dumps(results, indent=1, default=json_default))
    report.write_report(results, out)
    return results


def _suite(name, config, out, log) -> dict:
    if name == "dynamics":
        from hairwarp.benchmarks.dynamics import suite_dynamics

        return suite_dynamics(config, log)
    if name == "accuracy":
        from hairwarp.benchmarks.accuracy import suite_accuracy

        return suite_accuracy(config, out, log)
    if name == "stability":
        from hairwarp.benchmarks.stability import suite_stability

        return suite_stability(config, log)
    if name == "scaling":
        from hairwarp.benchmarks.scaling import suite_scaling

        return suite_scaling(config, log)
    if name == "budget":
        from hairwarp.benchmarks.budget import suite_budget

        return suite_budget(config, out, log)
    if name in EXTRA_SUITES:
        import importlib

        module, function = EXTRA_SUITES[name]
        return getattr(importlib.import_module(module), function)(config, out, log)
    raise ValueError(f"unknown benchmark suite {name!r}; choose one of {', '.join([*SUITES, *EXTRA_SUITES])} or all")


def json_default(value):
    """``json.dumps(..., default=json_default)``: numpy scalars and arrays, paths and objects with ``to_dict``
    (scenes) as plain JSON values."""
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "to_dict"):
        return value.to_dict()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m hairwarp.bench", description="Benchmarks of the strand solver.")
    parser.add_argument("suite", nargs="?", default="all", metavar="SUITE",
                        help=f"one of {', '.join([*SUITES, *EXTRA_SUITES])}, or all (default: the first "
                             f"{len(SUITES)})")
    parser.add_argument("--quick", action="store_true", help="small sizes, about a minute (smoke run)")
    parser.add_argument("--device", default=None, metavar="D", help="Warp device; cuda adds a CUDA column")
    parser.add_argument("--out", default=None, metavar="DIR", help="output folder (default: docs/ of the checkout)")
    parser.add_argument("--format", choices=("human", "json"), default="human", help="what to print at the end")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    return parser


def _child(request_json: str) -> int:
    import warp as wp

    from hairwarp.benchmarks.common import GATE, RESULT_TAG, child_result
    from hairwarp.benchmarks.peers import run_request

    wp.config.quiet = True
    GATE.enabled = False  # the parent waited for idle cores before starting this child
    result = child_result(run_request, json.loads(request_json))
    print(RESULT_TAG + json.dumps(result, default=json_default), flush=True)
    return 0


def main(args=None) -> int:
    """Entry of ``hairwarp bench`` (``args``: a Namespace with suite, quick, device, out, format) and of
    ``python -m hairwarp.bench`` (``args``: None or a list of strings)."""
    if args is None or isinstance(args, (list, tuple)):
        args = build_parser().parse_args(args)
    if getattr(args, "child", None):
        return _child(args.child)
    from hairwarp.benchmarks.common import BenchConfig

    suite = (getattr(args, "suite", None) or "all").lower()
    if suite != "all" and suite not in SUITES and suite not in EXTRA_SUITES:
        names = ", ".join([*SUITES, *EXTRA_SUITES])
        raise ValueError(f"unknown benchmark suite {suite!r}; choose one of {names} or all")
    suites = list(SUITES) if suite == "all" else [suite]
    device = getattr(args, "device", None) or "cpu"
    quick = bool(getattr(args, "quick", False))
    config = BenchConfig.quick_preset(device) if quick else BenchConfig.full(device)
    config.threads = int(getattr(args, "threads", None) or 0)
    out = Path(args.out) if getattr(args, "out", None) else default_out(quick)
    results = run_suites(suites, config, out, _log_to_stderr)
    if getattr(args, "format", "human") == "json":
        print(json.dumps(results, indent=1, default=json_default))
    else:
        from hairwarp.benchmarks.report import summary_lines

        print("\n".join(summary_lines(results, suites)))
        print(f"\nwrote {out / JSON_NAME}, {out / REPORT_NAME} and the charts ({results['wall_s']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
