"""Benchmark suites of ``hairwarp bench``: speed, accuracy, stability and scaling of the solver, and the
modelling budget of the shipped scenes (``budget``: the cheapest settings within a stated error bound).

Each suite is a function ``suite_<name>(config, log) -> dict`` returning plain JSON data;
``hairwarp.bench`` runs them, writes the JSON, the charts and the markdown report. Peer
simulators (Pinocchio, MuJoCo, Newton) run in child processes with a timeout, so a missing
package or a crash in one of them is recorded, not fatal.
"""

SUITES = ("dynamics", "accuracy", "stability", "scaling", "budget")
