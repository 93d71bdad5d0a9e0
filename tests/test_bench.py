"""Smoke test of ``hairwarp bench`` on tiny sizes: the JSON has its fields, ratios and goals follow from
the measured figures, the report and charts are written; plus the pieces the suites rely on (the grid
bisection against brute force, the exponent fit against a closed form, the stability test's energy
against Pinocchio). Speed is never asserted."""

import dataclasses
import json
import math

import numpy as np
import pytest

from hairwarp import bench
from hairwarp.benchmarks.common import BenchConfig, child_result, fit_exponent, run_child
from hairwarp.benchmarks.stability import EnergyMeter, bisect_grid, stability_model
from hairwarp.solver import Solver

# float32 state against Pinocchio's float64 energies of the same configuration
ENERGY_RTOL = 1e-4
# ratios are stored as computed from the stored figures; only float formatting separates them
RATIO_RTOL = 1e-12


def tiny_config():
    return dataclasses.replace(
        BenchConfig.quick_preset(),
        dyn_configs=[(4, 5)],
        dyn_peers=("pinocchio", "mujoco_euler"),
        block_steps=4,
        blocks=2,
        warmup=1,
        graph_block=2,
        ours_budget_s=0.2,
        peer_budget_s=0.2,
        acc_ref_dt=1e-4,
        acc_duration=0.5,
        acc_dts=(1e-3,),
        acc_integrators=("semi_implicit", "implicit_joints"),
        acc_peer_dts={"pinocchio_euler": (1e-3,)},
        acc_cost_strands=4,
        conv_segments=(4, 8),
        stab_stiffness=(1e-3,),
        stab_mujoco_stiffness=(1e-3,),
        stab_duration=0.05,
        stab_grid_bits=2,
        stab_segments=(5,),
        stab_segment_stiffness=(1e-3,),
        stab_mass_ratios=(1.0, 0.1),
        stab_side_duration=0.02,
        scale_strands=(4, 8),
        scale_segments=(4, 8),
        scale_budget_s=0.05,
        dense_counts=(50,),
        stages=("dense interpolation + Hermite",),
        quiet_gate=False,
    )


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    results = bench.run_suites(["dynamics", "accuracy", "stability", "scaling"], tiny_config(), out,
                               log=lambda msg: None)
    return out, results


def test_json_has_machine_and_suites(run):
    out, results = run
    data = json.loads((out / bench.JSON_NAME).read_text())
    assert data == json.loads(json.dumps(results, default=bench.json_default))
    m = data["machine"]
    for key in ("cpu", "cores", "python", "date", "versions"):
        assert m[key], key
    for pkg in ("warp", "numpy", "pin", "mujoco", "newton"):
        assert pkg in m["versions"]
    assert set(data["suites"]) == {"dynamics", "accuracy", "stability", "scaling"}
    for suite in data["suites"].values():
        assert suite["quick"] is True and suite["machine"]["date"]


def test_dynamics_ratios_follow_from_measured_figures(run):
    d = run[1]["suites"]["dynamics"]
    (cfg,) = d["configs"]
    G, S = cfg["G"], cfg["S"]
    for row in cfg["hairwarp"]["cpu"].values():
        best = row[row["best_mode"]]
        assert best["status"] == "ok" and best["finite"]
        assert math.isclose(row["seg_steps_per_s"], G * S / best["step_s"], rel_tol=RATIO_RTOL)
        assert row["seg_steps_per_s"] == max(row[m]["seg_steps_per_s"] for m in ("launch", "graph"))
    assert {r["peer"] for r in cfg["ratios"]} >= {"pinocchio", "mujoco_euler"}
    for r in cfg["ratios"]:
        peer = cfg["peers"][r["peer"]]
        if peer["status"] != "ok":
            assert r["ratio"] is None
            continue
        parent = {"pinocchio_aba_floor": "pinocchio", "mujoco_euler_c_only": "mujoco_euler"}.get(r["peer"], r["peer"])
        bracket = cfg["peers"][parent]["hairwarp_bracket"]
        before, after = bracket["before"][r["integrator"]], bracket["after"][r["integrator"]]
        assert math.isclose(r["ours_seg_steps_per_s"], math.sqrt(before * after), rel_tol=RATIO_RTOL)
        assert {before, after} <= set(cfg["hairwarp_over_run"][r["integrator"]]["samples"])
        assert math.isclose(r["ratio"], r["ours_seg_steps_per_s"]
                            / peer["seg_steps_per_s"], rel_tol=RATIO_RTOL)
        if r["goal"] is None:
            assert r["meets"] is None
        else:
            assert r["meets"] == (r["ratio"] >= r["goal"])
    pin = cfg["peers"]["pinocchio"]
    if pin["status"] == "ok":
        assert math.isclose(pin["seg_steps_per_s"], G * S / (pin["step_ms"] / 1e3), rel_tol=1e-9)
        assert cfg["peers"]["pinocchio_aba_floor"]["seg_steps_per_s"] > 0
    assert d["cuda"]["device"] is None and d["cuda"]["reason"]
    assert d["profile"] and d["overhead_1x20"]
    for p in d["profile"]:
        # every launch of a step is timed, at the executor where it replays its prepared launches (the table of
        # "Where a step's time goes" once came out empty), and when it runs (a chain of launches held for its end
        # once timed at 0.2 % of the step): the calls take a large share of the step's time, and no more than all of
        # it (the share is the kernel's against Python's per-step work, about half on this tiny model, less with the
        # machine loaded: a tenth tells the two apart)
        assert p["calls_per_step"] >= 1 and p["calls"], p
        calls_ms = sum(c["ms_per_step"] for c in p["calls"].values())
        assert 0.1 * p["wall_ms_per_step"] <= calls_ms <= p["wall_ms_per_step"], p


def test_accuracy_errors_and_reference_cache(run):
    out, results = run
    a = results["suites"]["accuracy"]
    assert a["reference"]["source"]
    assert list(out.glob("accuracy_reference_*.npz"))
    ours = [m for m in a["methods"] if m["kind"] == "hairwarp"]
    assert {m["integrator"] for m in ours} == {"semi_implicit", "implicit_joints"}
    for m in ours:
        (r,) = m["runs"]
        assert 0.0 < r["rms_0.5"] <= r["max_0.5"]
        assert math.isclose(r["cpu_s_per_sim_s"], m["cost"]["s_per_strand_step"] / r["dt"], rel_tol=RATIO_RTOL)
    conv = a["convergence"]
    for variant in conv["variants"].values():
        errors = [row["max_vertex_error_m"] for row in variant["rows"]]
        assert errors[1] < errors[0]
    # a second run reads the cached reference instead of recomputing it
    from hairwarp.benchmarks.accuracy import reference_tips

    again = reference_tips(tiny_config(), out, lambda msg: None)
    assert again["cached"]


def test_stability_and_scaling_fields(run):
    out, results = run
    s = results["suites"]["stability"]
    assert {"semi_implicit", "implicit_joints"} <= set(s["vs_stiffness"])
    for rows in s["vs_stiffness"].values():
        for row in rows:
            assert row["max_stable_dt"] is None or 1e-5 <= row["max_stable_dt"] <= 1 / 24 + 1e-12
    assert s["mujoco"]["status"] in ("ok", "absent")
    assert set(s["findings"]) >= {"implicit_stable_semi_not_at_frame_dt", "implicit_fails_at_frame_dt"}
    sc = results["suites"]["scaling"]
    assert sc["meets"] == (sc["max_exponent"] <= 1.1)
    assert {st["stage"] for st in sc["stages"]} >= {"dense interpolation + Hermite"}
    assert all(st["status"] in ("ok", "not available", "error") for st in sc["stages"])
    report = (out / "benchmarks.md").read_text()
    assert "CUDA: absent" in report
    for name in ("bench_dynamics.png", "bench_accuracy.png", "bench_convergence.png", "bench_stability.png",
                 "bench_scaling.png"):
        assert (out / name).stat().st_size > 1000, name


def test_failing_or_missing_peer_is_reported_not_raised():
    def missing(_):
        raise ModuleNotFoundError("no module", name="not_a_package")

    assert child_result(missing, {})["status"] == "absent"
    res = run_child({"kind": "throughput", "peer": "no_such_peer", "G": 1, "S": 2}, timeout_s=60)
    assert res["status"] == "error" and "no_such_peer" in res["message"]


def test_bisect_grid_matches_brute_force():
    rng = np.random.default_rng(3)
    n_grid, n_items = 33, 12
    limits = rng.integers(-1, n_grid, size=n_items)  # item j stable at index i iff i <= limits[j]
    calls = []

    def probe(idx, items):
        calls.append(idx)
        return {j: idx <= limits[j] for j in range(n_items)}

    found, _ = bisect_grid(n_grid, n_items, probe)
    expected = [None if lim < 0 else int(lim) for lim in limits]
    assert found == expected
    assert len(set(calls)) < n_grid  # fewer simulations than a scan of the grid


def test_fit_exponent_of_a_power_law():
    x = np.array([10.0, 30.0, 100.0, 300.0])
    assert math.isclose(fit_exponent(x, 2.5 * x**1.5), 1.5, rel_tol=1e-12)
    assert fit_exponent([1.0], [1.0]) is None


def test_energy_meter_matches_pinocchio():
    pin = pytest.importorskip("pinocchio")
    from hairwarp.benchmarks.peers import pinocchio_chain

    S = 6
    model = stability_model(S, [0.0], 0.0)
    state = model.state()
    rng = np.random.default_rng(7)
    q = rng.normal(size=(S, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    qd = rng.normal(scale=3.0, size=(S, 3))
    state.joint_q.assign(q.astype(np.float32))
    state.joint_qd.assign(qd.astype(np.float32))
    Solver(model).forward_kinematics(state, model.control())
    ours = EnergyMeter(model)(state)[0]

    pm = pinocchio_chain(S)
    data = pm.createData()
    qf = q.astype(np.float32).astype(float)
    qf /= np.linalg.norm(qf, axis=1, keepdims=True)
    qv, vv = qf.reshape(-1), qd.astype(np.float32).astype(float).reshape(-1)
    expected = pin.computeKineticEnergy(pm, data, qv, vv) + pin.computePotentialEnergy(pm, data, qv)
    assert ours == pytest.approx(expected, rel=ENERGY_RTOL)


# ---------------------------------------------------------------------------------------------
# budget suite: its metrics against numpy by hand, its picks recomputed from its own rows


def test_budget_tip_error_against_brute_force():
    from hairwarp.benchmarks.budget import tip_rms_error

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(5, 7, 3)), rng.normal(size=(5, 7, 3))
    total = sum(float(np.sum((a[f, g] - b[f, g]) ** 2)) for f in range(5) for g in range(7))
    assert tip_rms_error(a, b) == pytest.approx(math.sqrt(total / 35), rel=1e-12)
    # one tip of four off by 3-4-5 mm in one frame of two: sqrt(0.005^2 / 8)
    c = np.zeros((2, 4, 3))
    d = c.copy()
    d[1, 2] = (0.003, 0.004, 0.0)
    assert tip_rms_error(c, d) == pytest.approx(0.005 / math.sqrt(8), rel=1e-12)
    assert tip_rms_error(c, c) == 0.0
    with pytest.raises(ValueError):
        tip_rms_error(c, d[:, :3])


def test_budget_coverage_mask_and_iou_against_hand_counts():
    from hairwarp.benchmarks.budget import Grid, coverage_mask, silhouette_iou

    # screen x = world x, screen y = world z; 4 mm pixels from the origin
    grid = Grid(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), (0.0, 0.0), 0.004, (10, 12))
    # a horizontal curve through pixel row 0, columns 0-9, and a vertical one in column 5, rows 5-7; the jump
    # from the first curve's end to the second's start is no segment
    points = np.array([[0.0005, 0.3, 0.0005], [0.0395, -0.2, 0.0005],
                       [0.0205, 0.0, 0.0205], [0.0205, 0.0, 0.0305]])
    mask = coverage_mask(points, np.array([2, 2]), grid)
    expected = np.zeros((10, 12), dtype=bool)
    expected[0, 0:10] = True
    expected[5:8, 5] = True
    np.testing.assert_array_equal(mask, expected)
    # a point off the grid lands on the border pixel
    off = coverage_mask(np.array([[1.0, 0.0, -1.0]]), np.array([1]), grid)
    assert off[0, 11] and off.sum() == 1

    rng = np.random.default_rng(5)
    a, b = rng.random((9, 11)) < 0.4, rng.random((9, 11)) < 0.4
    inter = sum(1 for i in range(9) for j in range(11) if a[i, j] and b[i, j])
    union = sum(1 for i in range(9) for j in range(11) if a[i, j] or b[i, j])
    assert silhouette_iou(a, b) == pytest.approx(inter / union, rel=1e-12)
    assert silhouette_iou(a, a) == 1.0
    assert silhouette_iou(np.zeros((3, 3), bool), np.zeros((3, 3), bool)) == 1.0
    shifted = np.roll(expected, 1, axis=0)  # the curves one pixel up share only column 5's rows 6-7
    assert silhouette_iou(expected, shifted) == pytest.approx(2 / (13 + 13 - 2), rel=1e-12)


def test_budget_cheapest_within_bound_picks_from_rows():
    from hairwarp.benchmarks.budget import IOU_BOUND, TIP_BOUND_M, applicable, cheapest_within

    rows = [
        {"label": "ref", "status": "ok", "cost_s": 0.10, "tip_rms_m": 0.0, "iou": 1.0},
        {"label": "cheap but off", "status": "ok", "cost_s": 0.01, "tip_rms_m": 2 * TIP_BOUND_M, "iou": 0.99},
        {"label": "cheap, bad look", "status": "ok", "cost_s": 0.02, "tip_rms_m": 0.0, "iou": IOU_BOUND - 0.01},
        {"label": "unstable", "status": "unstable", "cost_s": 0.005, "tip_rms_m": None, "iou": None},
        {"label": "fits", "status": "ok", "cost_s": 0.05, "tip_rms_m": TIP_BOUND_M, "iou": IOU_BOUND},
        {"label": "fits, dearer", "status": "ok", "cost_s": 0.07, "tip_rms_m": 0.0, "iou": 1.0},
    ]
    assert cheapest_within(rows) == "fits"
    assert not applicable({"overrides": ['head.shape="mesh"', 'head.file="/tmp/x.ply"']})
    assert applicable({"overrides": ["sim.segments=12"]})
    assert cheapest_within(rows[:4]) == "ref"
    assert cheapest_within(rows[1:4]) is None


def test_budget_combined_picks_back_off_the_one_nearest_the_bound():
    """Where the picks together pass the bound, the combined run gives back the pick with the least room on its
    own: the smaller share of the bound's room left by its tip error and by its look."""
    from hairwarp.benchmarks.budget import IOU_BOUND, TIP_BOUND_M, _margin

    assert _margin({"tip_rms_m": 0.0, "iou": 1.0}) == 1.0
    assert _margin({"tip_rms_m": TIP_BOUND_M, "iou": 1.0}) == 0.0
    assert _margin({"tip_rms_m": None, "iou": IOU_BOUND}) == 0.0
    segments = {"tip_rms_m": 0.485 * TIP_BOUND_M, "iou": 0.966}  # long_hair's 8 segments
    dense = {"tip_rms_m": None, "iou": 0.952}  # its 1,000 dense strands
    contacts = {"tip_rms_m": 0.303 * TIP_BOUND_M, "iou": 0.985}  # its hair contacts off
    assert min((segments, dense, contacts), key=_margin) is dense
    assert abs(_margin(segments) - (0.966 - IOU_BOUND) / (1.0 - IOU_BOUND)) < 1e-12


@pytest.fixture(scope="module")
def budget_tiny():
    from pathlib import Path

    from hairwarp.benchmarks.budget import Choice, Plan, bench_scene

    path = Path(__file__).resolve().parents[1] / "scenes" / "tiny.toml"
    plan = Plan("tiny", path, ["sim.segments=12", "sim.substeps=16"], 0.2, [
        Choice("segments", "sim.segments", [("12", []), ("4", ["sim.segments=4"]), ("8", ["sim.segments=8"])], "8"),
        Choice("substeps", "sim.substeps", [("16", []), ("2", ["sim.substeps=2"]), ("8", ["sim.substeps=8"])], "8"),
        Choice("dense", "dense.count", [("200", ["dense.count=200"]), ("800", ["dense.count=800"])], "800",
               dense=True),
    ], base=["dense.count=800"], quick=True)
    return bench_scene(plan)


def test_budget_tiny_scene_picks_the_cheapest_within_bound(budget_tiny):
    from hairwarp.benchmarks.budget import IOU_BOUND, MIN_SAVING, TIP_BOUND_M, md_budget, within

    s = budget_tiny
    assert s["status"] == "ok" and s["strands"] == 8 and s["frames"] == 6
    for ch in s["choices"]:
        ok = [r for r in ch["rows"] if r["status"] == "ok" and (r["tip_rms_m"] is None or r["tip_rms_m"] <= TIP_BOUND_M)
              and (r["iou"] is None or r["iou"] >= IOU_BOUND)]
        expected = min(ok, key=lambda r: r["cost_s"])["label"] if ok else None
        assert ch["cheapest"] == expected, ch["name"]
        assert [r["label"] for r in ch["rows"] if r["cheapest_within_bound"]] == ([expected] if expected else [])
        for r in ch["rows"]:
            assert r["cost_s"] > 0
            if not ch["dense"] and not r.get("reference") and r["status"] == "ok":
                assert r["tip_rms_m"] > 0  # another model moves the tips: the metric can fail
    dense = next(ch for ch in s["choices"] if ch["dense"])
    assert [r["iou"] for r in dense["rows"]][1] == 1.0 and dense["rows"][0]["iou"] < 1.0
    # the combined run takes each choice's pick, or the shipped option when the pick saves too little or was
    # dropped because the picks together passed the bound (then the run ends within it, or with no pick left)
    picked, dropped = [], s["combined"]["dropped"]
    for ch in s["choices"]:
        pick = next((r for r in ch["rows"] if r["cheapest_within_bound"]), None)
        shipped = next(r for r in ch["rows"] if r["shipped"])
        if pick and within(shipped) and (pick["cost_s"] > (1 - MIN_SAVING) * shipped["cost_s"]
                                         or any(".file=" in o for o in pick["overrides"])):
            pick = shipped
        if pick and ch["key"] in dropped:
            pick = shipped
        if pick and not ch["dense"]:
            picked += pick["overrides"]
        if pick:
            assert s["combined"]["picks"][ch["key"]] == pick["label"]
    assert s["combined"]["overrides"] == picked
    text = "\n".join(md_budget({"scenes": [s], "skipped": [{"name": "x", "reason": "absent"}]}))
    assert "### `tiny`" in text and "`x` skipped: absent" in text


# ---------------------------------------------------------------------------------------------
# robustness suite: its smallest pieces on the tiny scene


def test_robustness_rest_structure_and_free_strands_settle(tmp_path):
    from hairwarp.benchmarks.robustness import bench_rest, bench_sweep, chart_grid, chart_rest

    rest = bench_rest(["tiny"], duration=2.0, second=2)
    (row,) = rest["rows"]
    assert row["status"] == "ok" and row["scene"] == "tiny"
    for label in ("colliders", "no_colliders"):
        r = row[label]
        assert r["fault"] is None and not r["nan"] and r["frames_done"] == 60
        assert len(r["rms_speed_per_second_mm_s"]) == 2 and len(r["rms_speed_per_frame_mm_s"]) == 60
        assert 0.0 <= r["moving_tips_fraction"] <= 1.0
    assert row["colliders"]["second_mm_s"] == row["colliders"]["rms_speed_per_second_mm_s"][1]
    assert row["ratio"] == pytest.approx(row["colliders"]["second_mm_s"] / row["no_colliders"]["second_mm_s"])
    assert isinstance(row["meets_speed"], bool) and isinstance(row["meets_ratio"], bool)
    assert set(row["resting"]) == {"vertices", "max_mm", "rms_mm"}
    sticky = row["sticky"]
    assert sticky["fault"] is None and sticky["frames_done"] == 60 and set(sticky["resting"]) == set(row["resting"])
    assert sticky["ratio"] == pytest.approx(sticky["second_mm_s"] / row["no_colliders"]["second_mm_s"])
    # the sticky run's scene really carries the friction on every collider
    from hairwarp.benchmarks.robustness import STICKY_FRICTION, build, head_still, raw_scene
    from hairwarp.benchmarks.robustness import sticky as make_sticky
    scene = build(make_sticky(head_still(raw_scene("long_hair_shoulders"))), "long_hair_shoulders")
    assert scene.head.friction == STICKY_FRICTION and scene.colliders
    assert all(c.friction == STICKY_FRICTION for c in scene.colliders)
    # With the head still and nothing to touch, the strands only lose energy (drag, damping): the tips slow down
    # from one second to the next.
    free = row["no_colliders"]["rms_speed_per_second_mm_s"]
    assert free[1] < 0.8 * free[0]
    # the frame-rate runs: 2 substeps and one step a frame, each the scene's whole time
    assert rest["frame_rate_substeps"] == 2 and rest["one_step_substeps"] == 1
    for label in ("frame_rate", "one_step"):
        assert row[label]["fault"] is None and row[label]["frames_done"] == 60
        assert row[label]["second_mm_s"] == row[label]["rms_speed_per_second_mm_s"][1]

    sweep = bench_sweep((8,), (1,), (2e-4,), 0.2, scene_name="tiny")
    assert len(sweep["cells"]) == 2  # links and contacts on, off
    assert {c["status"] for c in sweep["cells"]} <= {"ok", "fault", "nan", "burst"}
    assert sum(sweep["counts"].values()) == 2
    assert chart_rest(rest, None, tmp_path / "rest.png").stat().st_size > 0
    assert chart_grid(sweep, tmp_path / "grid.png").stat().st_size > 0



def test_robustness_summary_line_names_what_misses_its_goal():
    """The report's summary line of the robustness suite counts each part's cases that meet their goal and names the
    ones that do not: a scene whose rest misses one of its three goals, a convergence variant below first order."""
    from hairwarp.benchmarks.robustness import summary_md

    def rest(scene, resting=True):
        return {"scene": scene, "status": "ok", "meets_speed": True, "meets_ratio": True, "meets_resting": resting}

    data = {
        "rest": {"rows": [rest("tiny"), rest("long_hair", resting=False), {"scene": "ratboy_mohawk",
                                                                            "status": "skipped"}]},
        "sweep": {"counts": {"ok": 3}, "cells": [{}, {}, {}], "meets": True},
        "frame_rate": {"rows": [{"scene": "tiny", "status": "ok", "2": {"meets": True}, "1": {"meets": True}}]},
        "teleport": {"rows": [{"case": "teleport", "meets": True}]},
        "extreme": {"scenes": [{"scene": "long_hair", "rows": [{"case": "spin", "meets": True}]}]},
        "convergence": {"variants": {"links": {"meets": True, "order": 1.1}, "no links": {"meets": False, "order": 0.5},
                                     "free hair": {"meets": None, "order": 0.9}}},
    }
    line = summary_md(data)
    assert "at rest with the head still 1 of 2 ✗ (long_hair)" in line, line
    assert "stability grid 3 of 3 cells ✓" in line and "frame-rate steps 1 of 1 ✓" in line, line
    assert "convergence in the step 1 of 2 ✗ (no links, order 0.5)" in line and "free hair" not in line, line


def test_robustness_rest_redraws_a_missed_ratio_and_judges_the_means(monkeypatch):
    from hairwarp.benchmarks import robustness as rb

    # the figures alone: four pairs, the ratio of their means (not the mean of their ratios)
    d = rb.rest_redraws((1.4, 1.0), [(1.0, 1.0), (0.6, 0.5), (1.0, 1.5)])
    assert d["ratios"] == pytest.approx([1.4, 1.0, 1.2, 2.0 / 3.0])
    assert d["ratio_of_means"] == pytest.approx(4.0 / 4.0)
    assert d["perturbations"] == [0.0, *rb.REST_REDRAWS]
    assert rb.rest_redraws((1.0, 1.0), [(None, 1.0)])["ratio_of_means"] is None  # a faulted run judges nothing
    # through the suite: a goal every run misses makes the tiny scene redraw; its runs are the perturbed scenes
    monkeypatch.setattr(rb, "GOAL_REST_RATIO", 0.0)
    seen = []
    real = rb._rest_second

    def spy(raw, name, duration, second):
        seen.append((raw["sim"]["gravity"][2], bool(raw.get("head", {}).get("shape") == "none")))
        return real(raw, name, duration, second)

    monkeypatch.setattr(rb, "_rest_second", spy)
    (row,) = rb.bench_rest(["tiny"], duration=1.0, second=1)["rows"]
    r = row["redraws"]
    assert len(r["ratios"]) == 4 and r["ratios"][0] == pytest.approx(row["ratio"])
    assert r["ratio_of_means"] == pytest.approx(sum(r["colliders_mm_s"]) / sum(r["no_colliders_mm_s"]))
    assert row["meets_ratio"] is False
    g = -9.81
    assert sorted(seen) == sorted((g * (1.0 + k * rb.PERTURBATION), free) for k in rb.REST_REDRAWS
                                  for free in (False, True))
    assert "4 draws" in rb._ratio_cell(row) and "of the means" in rb._ratio_cell(row)

@pytest.mark.slow
def test_robustness_grid_runs_cells_near_the_limit_again_and_counts_them(monkeypatch):
    """A cell whose fastest vertex comes near the burst speed runs again with gravity changed (here every cell: the
    share set to 0); a rerun that bursts fails the grid although every cell of the grid itself is ok."""
    from hairwarp.benchmarks import robustness

    monkeypatch.setattr(robustness, "NEAR_FRACTION", 0.0)
    grid = robustness.bench_sweep([8], [2], [2e-4], duration=0.2, scene_name="tiny")
    cell = grid["cells"][0]
    assert cell["status"] == "ok" and grid["near"] == 2 and grid["near_not_ok"] == 0 and grid["meets"]
    changes = [r["gravity_change"] for r in cell["reruns"]]
    assert changes == [c * robustness.PERTURBATION for c in robustness.NEAR_RERUNS]
    assert all(r["status"] == "ok" and r["max_speed_m_s"] > 0.0 for r in cell["reruns"])

    calls = []
    plain = robustness.classify

    runs = 1 + len(robustness.NEAR_RERUNS)  # a cell's base run, then its reruns

    def bursts_when_run_again(run):  # each cell's last rerun
        calls.append(run)
        return "burst" if len(calls) % runs == 0 else plain(run)

    monkeypatch.setattr(robustness, "classify", bursts_when_run_again)
    grid = robustness.bench_sweep([8], [2], [2e-4], duration=0.2, scene_name="tiny")
    assert grid["counts"]["ok"] == 2 and grid["near_not_ok"] == 2 and not grid["meets"]


def test_robustness_grid_counts_frames_taken_again_after_a_fault(monkeypatch, tmp_path):
    """A cell whose frames fault at its step and run when taken again in twice the steps (a still head in a 700 m/s
    wind at 2 substeps: tests/test_faults.py; the wind blows its tips at 20 m/s, over the burst bound, which is
    raised here) is ok; the grid records those frames, its report line names them and its chart hatches the cell."""
    from hairwarp.benchmarks import robustness

    monkeypatch.setattr(robustness, "BURST_M_S", 100.0)
    plain = robustness.raw_scene

    def windy(name):
        raw = robustness.set_key(plain(name), "head.motion", {"kind": "still"})
        return robustness.set_key(raw, "wind.velocity", [700.0, 0.0, 0.0])

    monkeypatch.setattr(robustness, "raw_scene", windy)
    grid = robustness.bench_sweep([8], [2], [2e-4], duration=0.2, scene_name="tiny")
    cells = {c["links_contacts"]: c for c in grid["cells"]}
    assert all(c["status"] == "ok" and c["frames_done"] == 6 for c in cells.values()), cells
    assert all(c["retaken"] >= 1 and c["retakes"][0] == (1, 4, "air drag (wind.velocity)") for c in cells.values())
    line = robustness._retaken_line(grid)
    assert line.startswith("- Frames taken again after a fault") and "frames 1 in 4" in line, line
    assert robustness.chart_grid(grid, tmp_path / "grid.png").stat().st_size > 0
    # without retries the same cells fault, and nothing is taken again
    monkeypatch.setattr(robustness, "raw_scene", lambda name: robustness.set_key(windy(name), "sim.fault_retries", 0))
    grid = robustness.bench_sweep([8], [2], [2e-4], duration=0.2, scene_name="tiny")
    assert grid["counts"]["fault"] == 2 and robustness._retaken_line(grid) == ""


def test_robustness_strand_spread_against_a_hand_count():
    """The convergence part's spread of the tip difference over the strands: 20 strands off by 1..20 mm in every
    frame give a median strand of 10.5 mm and the 10 worst strands' share of the mean square
    (11^2 + ... + 20^2) / (1^2 + ... + 20^2) = 2485 / 2870; a strand off in one frame of four counts half its
    offset (RMS over frames)."""
    from hairwarp.benchmarks.robustness import WORST_STRANDS, strand_spread

    reference = np.zeros((4, 20, 3))
    tips = reference.copy()
    tips[:, :, 0] = 1e-3 * np.arange(1, 21)
    out = strand_spread(tips, reference)
    assert WORST_STRANDS == 10
    # float64 throughout: the tolerances are round-off of sums of 20 terms
    assert abs(out["median_strand_mm"] - 10.5) < 1e-9 and abs(out["worst_share"] - 2485 / 2870) < 1e-12
    tips = reference.copy()
    tips[2, :, 1] = 2e-3  # one frame of four: RMS over frames 1 mm
    assert abs(strand_spread(tips, reference)["median_strand_mm"] - 1.0) < 1e-9


@pytest.mark.slow
def test_robustness_convergence_floor_on_the_tiny_scene():
    """The convergence part on the tiny scene at 1 and 2 substeps against 4: every run finishes, and its second
    reference run (gravity changed by PERTURBATION, relative) lands a finite, non-zero distance from the first: the
    change is 1e-5 of 9.81 m/s^2, a hundred times float32's resolution of it, so it reaches the tips."""
    from hairwarp.benchmarks.robustness import PERTURBATION, bench_convergence, perturbed, raw_scene

    gravity = raw_scene("tiny").get("sim", {}).get("gravity", [0.0, 0.0, -9.81])
    assert perturbed(raw_scene("tiny"))["sim"]["gravity"] == [g * (1.0 + PERTURBATION) for g in gravity]
    conv = bench_convergence((1, 2), 4, 0.3, scene_name="tiny", finer=(8,))
    assert conv["perturbation"] == PERTURBATION
    assert set(conv["variants"]) == {"links", "no links", "free hair", "colliders only"}
    for v in conv["variants"].values():
        assert v["reference_fault"] is None and all(r["fault"] is None for r in v["rows"])
        assert 0.0 < v["reference_again_mm"] < min(r["tip_rms_mm"] for r in v["rows"])
        # each run against the next finer, through the finer run; the first sensitivity run is the one above
        assert [d["substeps"] for d in v["successive"]] == [[1, 2], [2, 4], [4, 8]]
        assert all(d["tip_rms_mm"] > 0.0 for d in v["successive"])
        assert v["sensitivity"][0]["tip_rms_mm"] == v["reference_again_mm"]
        # a thousand times the change of gravity moves the tips farther (free hanging hair: about 1000 times)
        assert v["sensitivity"][-1]["tip_rms_mm"] > 10.0 * v["sensitivity"][0]["tip_rms_mm"]


def test_robustness_successive_differences_read_a_first_order_method_as_order_1():
    """Tips off the exact answer by c h (a first-order method, h = 1/n): each run against the next finer differs by
    c (h - h/2), halving with the step, order 1 at every halving; against the finest run the last halving reads
    log2(3) = 1.58 (the differences c (4h - h) and c (2h - h))."""
    from hairwarp.benchmarks.robustness import convergence_orders, halving_orders, successive_differences

    exact = np.zeros((5, 3, 3))
    runs = {n: {"fault": None, "tips": exact + [0.012 / n, 0.0, 0.0]} for n in (1, 2, 4, 8, 16)}
    pairs = successive_differences(runs)
    assert [d["substeps"] for d in pairs] == [[1, 2], [2, 4], [4, 8], [8, 16]]
    # float64: round-off of a few operations on millimetres
    assert np.allclose([d["tip_rms_mm"] for d in pairs], [6.0, 3.0, 1.5, 0.75], rtol=1e-12)
    assert np.allclose(halving_orders([d["tip_rms_mm"] for d in pairs]), 1.0, rtol=1e-12)
    rows = [{"fault": None, "dt": 1.0 / n, "tip_rms_mm": 12.0 * (1.0 / n - 1.0 / 16)} for n in (1, 2, 4, 8)]
    assert abs(convergence_orders(rows)["finest_order"] - np.log2(3.0)) < 1e-12
    runs[4]["fault"] = {"stage": "dynamics"}
    assert halving_orders([d["tip_rms_mm"] for d in successive_differences(runs)]) == [None, None, None]


def test_robustness_spin_keys_turn_at_the_spin_rate():
    """The extreme-motion suite's spin: keyframes 20 degrees apart whose interpolated head turns about z at
    3 rev/s between the first and the last interval (Catmull-Rom on evenly spaced keys of a constant rate is that
    rate), and whose pose at a key is the wrapped angle."""
    import math

    from hairwarp.benchmarks.robustness import spin_keys
    from hairwarp.motion import HeadMotion

    keys = spin_keys(0.2, 1.0, 3.0)
    assert len(keys) == 55 and all(-180.0 <= k["angle_deg"] <= 180.0 for k in keys)
    motion = HeadMotion.from_config({"kind": "keyframes", "keys": keys, "pivot": (0.0, 0.0, 1.49)})
    for t in (0.5, 0.77, 1.0):
        assert abs(motion.evaluate(t).angular_velocity[2] - 2.0 * math.pi * 3.0) < 1e-6
    s = motion.evaluate(0.2 + 7.0 / 54.0)  # the 8th key: 140 degrees
    assert abs(2.0 * math.degrees(math.atan2(s.rotation[2], s.rotation[3])) - 140.0) < 1e-6


def test_robustness_faster_motion_plays_the_scene_motion_faster():
    """The extreme-motion suite's faster motion: a keyframed head (``long_hair_shoulders``' nod) reaches at time
    ``t / 10`` the pose the shipped motion reaches at ``t``; a periodic one (``long_hair``'s turn) keeps its start
    and ramp and turns ten times as fast, so without them (set to 0 here) it too is the shipped pose at ``t / 10``."""
    from hairwarp.benchmarks.robustness import faster_motion, raw_scene
    from hairwarp.motion import HeadMotion

    nod = raw_scene("long_hair_shoulders")["head"]["motion"]
    turn = dict(raw_scene("long_hair")["head"]["motion"], start=0.0, ramp=0.0)
    for config, times in ((nod, (0.3, 0.75, 1.4)), (turn, (0.2, 0.6, 1.0))):
        shipped, fast = HeadMotion.from_config(config), HeadMotion.from_config(faster_motion(config, 10.0))
        for t in times:  # float64 on the host: the same poses to round-off, far below the bounds
            np.testing.assert_allclose(fast.evaluate(t / 10.0).rotation, shipped.evaluate(t).rotation, atol=1e-6)
            np.testing.assert_allclose(fast.evaluate(t / 10.0).angular_velocity,
                                       10.0 * np.asarray(shipped.evaluate(t).angular_velocity), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_robustness_newton_rod_rests_on_its_collider():
    """Newton's VBD rod released onto the peers' capsule for 1 s (the suite adds the floor): both runs finish finite
    with the figures of the MuJoCo peer; with shape contacts the rod's surface never goes more than 1 mm into the
    capsule, and without them the rod swings through it (its centre line more than 1 cm inside)."""
    try:
        import newton  # noqa: F401
    except ImportError as e:
        pytest.skip(f"newton is not importable: {e}")
    from hairwarp.benchmarks.common import RADIUS
    from hairwarp.benchmarks.robustness import PEER_NEWTON_ITERATIONS, PEER_SEGMENTS, newton_rest

    out = newton_rest({"duration": 1.0, "colliders": ["capsule"]})
    assert out["iterations"] == PEER_NEWTON_ITERATIONS and out["segments"] == PEER_SEGMENTS and out["newton"]
    assert set(out["results"]) == {"capsule"}
    for entry in out["results"].values():
        for label in ("contact", "no_contact"):
            r = entry[label]
            assert r["finite"] and r["frames_done"] == 30
            assert len(r["rms_speed_per_second_mm_s"]) == 1 and len(r["rms_speed_per_frame_mm_s"]) == 30
        rv = entry["contact"]["resting"]
        assert set(rv) == {"points", "max_mm"} and "resting" not in entry["no_contact"]
        assert entry["contact"]["min_clearance_mm"] > -1.0
    # the rod drapes over the capsule: some of its points lie on it in the last second
    assert out["results"]["capsule"]["contact"]["resting"]["points"] > 0
    assert out["results"]["capsule"]["no_contact"]["min_clearance_mm"] < -1e3 * RADIUS - 10.0


def test_single_layer_baseline_writes_what_the_cache_writer_writes(tmp_path):
    """The dense suite's baseline writer (one layer saved each frame) stores the same samples as the clip-layer
    cache: both read back with usd-core, frame by frame, bit for bit (both store the float32 points as given)."""
    from pxr import Usd, UsdGeom

    from hairwarp.benchmarks.dense import SingleLayerWriter
    from hairwarp.io.cache import CacheWriter

    rng = np.random.default_rng(3)
    counts = np.full(5, 4)
    frames = [rng.normal(size=(20, 3)).astype(np.float32) for _ in range(3)]
    paths = {"single": tmp_path / "single.usdc", "clips": tmp_path / "clips.usdc"}
    for name, cls in (("single", SingleLayerWriter), ("clips", CacheWriter)):
        cache = cls(paths[name], fps=30.0)
        cache.add_curves("hair", counts, widths=(1e-4, 2e-5), basis="catmullRom")
        for f, p in enumerate(frames):
            cache.write_frame(f, {"hair": (p, 2.0 * p)})
        cache.close()
    read = {}
    for name, path in paths.items():
        stage = Usd.Stage.Open(str(path))
        curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/hair"))
        read[name] = [(np.asarray(curves.GetPointsAttr().Get(f)), np.asarray(curves.GetVelocitiesAttr().Get(f)))
                      for f in range(len(frames))]
        assert list(curves.GetCurveVertexCountsAttr().Get()) == list(counts)
    for (ps, vs), (pc, vc), p in zip(read["single"], read["clips"], frames):
        np.testing.assert_array_equal(ps, p)
        np.testing.assert_array_equal(ps, pc)
        np.testing.assert_array_equal(vs, vc)


def test_threads_copies_throughput_of_sleeping_copies():
    """Copies that release the GIL and take 20 ms each run at once: their share of a call is 20 ms / N."""
    import time

    from hairwarp.benchmarks.threads import _time_copies

    for n in (1, 3):
        share = _time_copies([lambda: time.sleep(0.02)] * n, 0.1)
        # a sleep overshoots by scheduler slack (well under 5 ms here), never undershoots
        assert 0.02 / n <= share < 0.025 / n, (n, share)


def test_threads_frame_timings_run_the_same_frames():
    """Every whole-frame timing, on one thread, N or the copies, starts from the run's checkpoint: each runs the same
    frames of the motion, whichever side is faster and however many timings came before."""
    from hairwarp.benchmarks.threads import FRAMES_PER_TIMING, _time_frames, _time_frames_copies

    class Run:  # what the timings use of a Simulation: a frame counter they advance, checkpoint and restore
        def __init__(self):
            self.frame, self.ran = 10, []

        def advance(self):
            self.ran.append(self.frame)
            self.frame += 1

        def checkpoint(self):
            return {"frame": self.frame}

        def restore(self, saved):
            self.frame = saved["frame"]

    runs = [Run() for _ in range(3)]
    saved = [r.checkpoint() for r in runs]
    for _ in range(3):
        assert _time_frames(runs[0], saved[0], runs[0].advance) >= 0.0
        assert _time_frames_copies(runs[1:], saved[1:], [r.advance for r in runs[1:]]) >= 0.0
    expected = list(range(10, 10 + FRAMES_PER_TIMING)) * 3
    assert all(r.ran == expected for r in runs), [r.ran for r in runs]


def test_threads_sweep_times_the_frame_its_table_times(monkeypatch):
    """The sweep's frame of the default scene is the frame its scene table times, dense hair included
    (``FRAME_STAGE``): the report sets the two side by side as one measure taken twice."""
    from hairwarp.benchmarks import threads
    from hairwarp.runner import Simulation

    calls = []
    dense_curves = Simulation.dense_curves

    def counted(self, *args, **kwargs):
        calls.append(1)
        return dense_curves(self, *args, **kwargs)

    monkeypatch.setattr(Simulation, "dense_curves", counted)
    monkeypatch.setattr(threads, "SWEEP_SIZE", (4, 3))
    monkeypatch.setattr(threads, "WARMUP_FRAMES", 1)
    monkeypatch.setattr(threads, "FRAMES_PER_TIMING", 2)
    monkeypatch.setattr(threads.GATE, "enabled", False)
    data = threads.sweep([1], rounds=1, min_s=0.0, overrides=["groom.count=9", "dense.count=8", "sim.substeps=1"])
    assert data["rows"][0]["frame_ms"] > 0.0
    assert len(calls) == threads.FRAMES_PER_TIMING  # one dense evaluation a timed frame


def test_threads_report_states_goals_and_efficiency():
    from hairwarp.benchmarks.threads import md_threads

    rows = [{"stage": "dynamics (aba + integrate)", "t1_ms": 2.0, "tn_ms": 1.0, "speedup": 2.0,
             "copies_speedup": 1.6, "efficiency": 1.25},
            {"stage": "frame (detection, substeps, dense)", "t1_ms": 50.0, "tn_ms": 40.0, "speedup": 1.25,
             "copies_speedup": 1.8, "efficiency": 1.25 / 1.8}]
    scene = {"scene": "s.toml", "guides": 3, "segments": 4, "substeps": 8, "threads": 2, "rows": rows,
             "load_before": [0.0], "load_after": [0.0],
             "gate": {"rounds_under_load": 1, "rounds": 5, "others_busy_cores_max": 0.9, "threshold_cores": 0.35}}
    text = "\n".join(md_threads({"threads": 2, "cores": 2, "scenes": [scene]}))
    assert "after; 1 of 5 rounds began with other programs busy on >= 0.35 cores)" in text
    assert "| dynamics (aba + integrate) | 2.000 | 1.000 | 2.00x | 1.60x | 125 % |" in text
    assert "- dynamics: 2.00x (goal >= 1.9x on 2 cores: met); 2 independent copies reach 1.60x" in text
    assert "- frame: 1.25x (goal >= 1.8x on 2 cores: not met)" in text and "keeps 69 %" in text
    # the sweep's frame at the suite's thread count is the same measure as the scene's frame: set side by side
    sweep = {"dynamics": "d", "frame": "s.toml", "rows": [
        {"threads": 1, "dynamics_ms": 2.0, "dynamics_speedup": 1.0, "frame_ms": 48.0, "frame_speedup": 1.0},
        {"threads": 2, "dynamics_ms": 1.0, "dynamics_speedup": 2.0, "frame_ms": 30.0, "frame_speedup": 1.6}]}
    text = "\n".join(md_threads({"threads": 2, "cores": 2, "scenes": [scene], "sweep": sweep}))
    assert ("frame at 2 threads is the frame of the s.toml table above, timed again later in the run: 1.60x here "
            "against 1.25x there (30.00 ms against 40.00 ms on 2 threads, 48.00 against 50.00 on one)") in text



def test_join_gate_waits_for_the_probe_and_records_what_it_saw(monkeypatch):
    """The threads suite's join gate (``JoinGate``) starts a pair of timings once the join probe is back within
    ``JOIN_FRACTION`` of its usual value (the upper quartile of its probes so far, after ``JOIN_FIRST_PROBES``), waits
    no longer than ``JOIN_MAX_WAIT_S``, takes a pair again when the probe after it is low, and records every probe;
    one high outlier does not hold every pair after it."""
    from hairwarp.benchmarks import threads

    gate = threads.JoinGate(2)
    try:
        assert gate.probe(reps=2, rounds=1) > 0.0  # the real probe: its table timed on one thread and on two
        seen = iter([1.68, 2.10, 1.66, 1.69, 1.30, 1.35, 1.67, 1.64, 1.20])
        monkeypatch.setattr(gate, "probe", lambda: next(seen))
        monkeypatch.setattr(threads.time, "sleep", lambda seconds: None)
        first = [gate.wait() for _ in range(4)]  # 2.10, an outlier among them
        assert [r["probe"] for r in first] == [1.68, 2.10, 1.66, 1.69] and not any(r["low"] for r in first)
        fifth = gate.wait()  # 1.30 and 1.35 below 85 % of the upper quartile (1.69 or more): waits for 1.67
        assert fifth["probe"] == 1.67 and not fifth["low"]
        assert not gate.wait()["low"]  # 1.64: within
        monkeypatch.setattr(threads, "JOIN_MAX_WAIT_S", 0.0)
        assert gate.wait()["low"]  # 1.20, and no time to wait: timed anyway, and said so
        summary = gate.summary()
        assert (summary["pairs"], summary["low"], summary["min"], summary["median"]) == (7, 1, 1.20, 1.67)
        assert 1.68 <= summary["usual"] < 1.70 and gate.summary((6, 0, 0))["pairs"] == 1
        # a pair after which the probe is low is timed again: the second timing is kept
        seen = iter([1.68, 1.20, 1.67, 1.66])
        monkeypatch.setattr(threads, "JOIN_MAX_WAIT_S", 30.0)
        timings = iter([40.0, 30.0])
        assert gate.pair(lambda: next(timings)) == 30.0
        assert (gate.redone, gate.ended_low) == (1, 0)
        assert gate.summary(gate.mark())["redone"] == 0 and gate.summary()["redone"] == 1  # counted from a mark
    finally:
        gate.close()
    assert threads._join_words(summary).startswith(
        "the join probe 1.67x at the median of 7 pairs of timings, 1.20x at the lowest; 1 of 7 pairs began with it "
        "below 85 % of its usual 1.6")


def test_threads_speed_up_is_the_median_of_each_rounds_ratio():
    """Timings of a quiet 2-core machine (one-thread and two-thread dynamics of long_hair, ms, three rounds): the
    one-thread side ran at 1.88 ms in one round and 2.33-2.71 in the others. Its best against the other side's best
    says 1.63x; the rounds' own ratios are 1.33, 2.02 and 2.06, and their median 2.02x."""
    from hairwarp.benchmarks.threads import _paired

    one, two = [1.878, 2.328, 2.705], [1.416, 1.150, 1.313]
    assert abs(_paired(one, two) - 2.328 / 1.150) < 1e-12
    assert abs(min(one) / min(two) - 1.633) < 1e-3  # what the best rounds alone said


def test_threads_sweep_counts_and_its_goal_at_16():
    from hairwarp.benchmarks.threads import md_sweep, sweep_counts

    assert sweep_counts(1) == [1] and sweep_counts(2) == [1, 2] and sweep_counts(6) == [1, 2, 4, 6]
    assert sweep_counts(16) == [1, 2, 4, 8, 16]
    rows = [{"threads": n, "dynamics_ms": 20.0 / s, "dynamics_speedup": s, "frame_ms": 40.0 / f, "frame_speedup": f}
            for n, s, f in ((1, 1.0, 1.0), (16, 11.5, 5.0))]
    text = "\n".join(md_sweep({"dynamics": "2228 x 31", "frame": "long_hair.toml", "rows": rows}))
    assert "| 16 | 1.739 | 11.50x | 8.00 | 5.00x |" in text
    assert "dynamics at 16 threads: 11.5x (goal >= 12x: not met)" in text
    # no 16 in the sweep (a smaller machine): no verdict
    assert "goal" not in "\n".join(md_sweep({"dynamics": "d", "frame": "f", "rows": rows[:1]}))

def test_wedge_report_compares_workers_at_one_thread_and_the_threaded_worker():
    from hairwarp.benchmarks.wedge import md_wedge

    def run(workers, threads, wall):
        return {"workers": workers, "threads": threads, "config": [workers, threads], "wall_s": wall,
                "submit_to_last_result_s": wall - 2.0, "cluster_s": 2.0, "task_s_mean": 5.0, "simulate_s_mean": 4.9,
                "engine_s_mean": 0.01, "engine_s_max": 0.02, "others_busy_cores": 0.0, "load_average_start": [0.1]}

    runs = [run(1, 1, 60.0), run(2, 1, 32.0), run(1, 2, 40.0)]
    data = {"scene": "long_hair.toml", "variants": 8, "params": {"a": [1, 2]}, "frames": 60, "frames_shipped": 90,
            "cores": 2, "runs": runs, "all_runs": runs, "noop": {"median_s": 0.01, "max_s": 0.02, "tasks": 40},
            "speedup": 60.0 / 32.0, "goal_speedup": 1.8, "meets": True}
    text = "\n".join(md_wedge(data))
    assert "**Speed-up with 2 workers: 1.88×** (goal ≥ 1.8×: met)" in text
    assert "| 1 | 1 | 2 | **40.0** |" in text
    assert "One worker whose runs take 2 threads each: 40.0 s, the speed of 1.50× the one-thread worker against " \
           "1.88× for 2 workers, so a wedge fills the cores faster" in text


def test_a_failing_suite_leaves_the_report_of_those_that_finished(tmp_path, monkeypatch):
    """Suites run one after the other: when one raises, the report of the suites before it is still written (its
    JSON was), and the error goes on to the caller."""
    from hairwarp.benchmarks import report

    written = []

    def suite(name, config, out, log):
        if name == "second":
            raise RuntimeError("the second suite failed")
        return {"figure": 1.0}

    monkeypatch.setattr(bench, "_suite", suite)
    monkeypatch.setattr(report, "write_report", lambda results, out: written.append(sorted(results["suites"])))
    with pytest.raises(RuntimeError, match="the second suite failed"):
        bench.run_suites(["first", "second"], BenchConfig.quick_preset("cpu"), tmp_path, log=lambda m: None)
    assert written == [["first"]]
    assert json.loads((tmp_path / bench.JSON_NAME).read_text())["suites"]["first"]["figure"] == 1.0


def test_each_suite_names_the_machine_it_ran_on():
    """Suites of one report run at different times, on more than one kind of machine: each footer names its CPU,
    and the header lists which suites ran where when there is more than one."""
    from hairwarp.benchmarks.common import machine_words
    from hairwarp.benchmarks.report import _suite_machines

    assert machine_words({"cpu": "AMD EPYC", "cores": 2}) == " on AMD EPYC, 2 cores"
    assert machine_words({}) == ""
    one = {"a": {"machine": {"cpu": "X"}}, "b": {"machine": {"cpu": "X"}}}
    assert _suite_machines(one) == []
    two = {**one, "c": {"machine": {"cpu": "Y"}}}
    (line,) = _suite_machines(two)
    assert "X: a, b; Y: c" in line
