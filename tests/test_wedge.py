"""Wedges and batches on a real Dask ``LocalCluster`` (2 worker processes): the caches against the same scenes run
one by one, a worker killed mid-task, reruns that reuse complete tasks, faults as results, the command's errors
and Ctrl-C. Caches are read back through ``pxr.Usd`` directly, independently of hairwarp's writer and readers."""

import functools
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

import cloudpickle  # noqa: E402

from hairwarp import farm  # noqa: E402
from hairwarp.cli import main  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "scenes" / "tiny.toml"
FRAMES = 5
# Four variants: two bend stiffnesses x two dampings, few frames.
PARAMS = {"strands.bend_stiffness": ["1e-4", "1e-3"], "strands.damping": ["1e-7", "1e-6"]}
FIXED = [f"sim.frames={FRAMES}"]
# Bound on a wedge command in a subprocess.
CLI_TIMEOUT_S = 240

# The killing task functions below live in this module, which worker processes cannot import: send them by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _usd_arrays(path) -> dict:
    """Every authored attribute value of a stage at every time sample: (prim path, attribute, time) -> array."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    assert stage is not None, path
    out = {}
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            if not attr.HasAuthoredValue():
                continue
            times = attr.GetTimeSamples() or [Usd.TimeCode.Default()]
            for t in times:
                value = attr.Get(t)
                key = (str(prim.GetPath()), attr.GetName(), t if isinstance(t, float) else "default")
                try:
                    out[key] = np.array(value)
                except (TypeError, ValueError):
                    out[key] = value
    return out


def _assert_same_cache(a, b):
    arrays_a, arrays_b = _usd_arrays(a), _usd_arrays(b)
    assert arrays_a.keys() == arrays_b.keys()
    for key, value in arrays_a.items():
        other = arrays_b[key]
        if isinstance(value, np.ndarray):
            assert value.dtype == other.dtype and np.array_equal(value, other), key
        else:
            assert value == other, key


@pytest.fixture(scope="module")
def wedge4(tmp_path_factory):
    """A 4-variant wedge of tiny.toml on a local cluster of 2 worker processes: (out folder, records)."""
    out = tmp_path_factory.mktemp("wedge4")
    tasks = farm.wedge_tasks(TINY, PARAMS, out, overrides=FIXED)
    records = farm.run_tasks(tasks, out, workers=2)
    return out, records


def test_wedge_caches_match_the_scenes_run_one_by_one(wedge4, tmp_path):
    import hairwarp as hw

    out, records = wedge4
    assert [r["status"] for r in records] == ["ok"] * 4
    combos = [(b, d) for b in PARAMS["strands.bend_stiffness"] for d in PARAMS["strands.damping"]]
    for r, (bend, damping) in zip(records, combos, strict=True):
        assert r["values"] == {"strands.bend_stiffness": float(bend), "strands.damping": float(damping)}
        scene = hw.Scene.load(TINY, overrides=[*FIXED, f"strands.bend_stiffness={bend}", f"strands.damping={damping}"])
        alone = hw.simulate(scene, tmp_path / f"{r['name']}.usdc", progress=False)
        _assert_same_cache(r["cache"], alone.cache_path)
        assert r["frames"] == FRAMES == alone.frames
        assert Path(r["preview"]).is_file() and Path(r["folder"]) == out / r["name"]
    # the runs differ from each other: the wedge did vary the values
    a, b = _usd_arrays(records[0]["cache"]), _usd_arrays(records[3]["cache"])
    key = ("/World/Hair/guides", "points", float(FRAMES))
    assert not np.array_equal(a[key], b[key])


def test_wedge_writes_summaries_and_a_contact_sheet_row_per_variant(wedge4):
    import csv

    from PIL import Image

    out, records = wedge4
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [r["name"] for r in rows] == [r["name"] for r in records]
    assert {"strands.bend_stiffness", "strands.damping", "status", "frames", "seconds", "tip_travel_mean_m"} <= set(
        rows[0])
    assert json.loads((out / "summary.json").read_text())[2]["name"] == records[2]["name"]
    md = (out / "summary.md").read_text()
    assert all(r["name"] in md for r in records)
    # tip travel against the cache read back here: path length of each guide's last vertex over the frames
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(records[1]["cache"])
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    tips = np.cumsum(np.array(curves.GetCurveVertexCountsAttr().Get())) - 1
    path = np.stack([np.array(curves.GetPointsAttr().Get(float(f)))[tips] for f in range(FRAMES + 1)])
    travel = np.linalg.norm(np.diff(path, axis=0), axis=2).sum(axis=0)
    assert records[1]["tip_travel_mean_m"] == pytest.approx(travel.mean(), abs=1e-5)
    assert records[1]["tip_travel_max_m"] == pytest.approx(travel.max(), abs=1e-5)
    sheet = Image.open(out / "sheet.png")
    assert sheet.height >= 4 * 200 and sheet.width > sheet.height * 0.8  # 4 rows, a label column and 4 frames


def test_rerun_skips_complete_tasks_and_redoes_partial_ones(wedge4, tmp_path):
    src, records = wedge4
    out = tmp_path / "again"
    shutil.copytree(src, out)  # keeps the mtimes
    before = {r["name"]: (out / r["name"] / f"{r['name']}.usdc").stat().st_mtime_ns for r in records}
    marker_before = {r["name"]: (out / r["name"] / farm.MARKER).stat().st_mtime_ns for r in records}
    # the largest file of the cache: a layer in its clips folder, beside the small root layer
    truncated = max((p for p in (out / records[1]["name"]).rglob("*.usdc")), key=lambda p: p.stat().st_size)
    size = truncated.stat().st_size
    with open(truncated, "r+b") as f:
        f.truncate(size // 2)
    (out / records[2]["name"] / farm.MARKER).unlink()  # a run that stopped before its marker
    again = farm.run_tasks(farm.wedge_tasks(TINY, PARAMS, out, overrides=FIXED), out, workers=2)
    assert [r["skipped"] for r in again] == [True, False, False, True]
    assert [r["status"] for r in again] == ["ok"] * 4
    for i in (0, 3):
        name = records[i]["name"]
        assert (out / name / f"{name}.usdc").stat().st_mtime_ns == before[name]
        assert (out / name / farm.MARKER).stat().st_mtime_ns == marker_before[name]
    for i in (1, 2):
        name = records[i]["name"]
        assert (out / name / farm.MARKER).is_file()
        _assert_same_cache(out / name / f"{name}.usdc", records[i]["cache"])
    assert truncated.stat().st_size == size


def test_completion_needs_the_same_key_and_every_file_at_its_size(tmp_path):
    from hairwarp.scene import Scene

    scene = Scene.load(TINY)
    key = farm.scene_key(scene)
    assert key == farm.scene_key(Scene.load(TINY)) != farm.scene_key(scene.with_overrides(["strands.drag=0.02"]))
    (tmp_path / "a.usdc").write_bytes(b"12345")
    (tmp_path / farm.STATS).write_text(json.dumps({"name": "x", "cache": "a.usdc", "preview": None}))
    assert farm.completed_record(tmp_path, key) is None  # no marker
    marker = {"key": key, "files": {"a.usdc": 5, farm.STATS: (tmp_path / farm.STATS).stat().st_size}}
    (tmp_path / farm.MARKER).write_text(json.dumps(marker))
    assert farm.completed_record(tmp_path, key)["cache"] == str(tmp_path / "a.usdc")
    assert farm.completed_record(tmp_path, "another key") is None
    (tmp_path / "a.usdc").write_bytes(b"123")
    assert farm.completed_record(tmp_path, key) is None


def test_variants_grid_zip_and_values_with_commas():
    assert farm.split_values("1e-4, 3e-4,[0, 0, -9.8],\"a,b\"") == ["1e-4", "3e-4", "[0, 0, -9.8]", '"a,b"']
    grid = farm.combinations({"a": ["1", "2"], "b": ["x", "y", "z"]}, "grid")
    assert [[v for _, v in c] for c in grid] == [["1", "x"], ["1", "y"], ["1", "z"], ["2", "x"], ["2", "y"],
                                                 ["2", "z"]]
    assert [[v for _, v in c] for c in farm.combinations({"a": ["1", "2"], "b": ["x", "y"]}, "zip")] == [
        ["1", "x"], ["2", "y"]]
    with pytest.raises(ValueError, match="--zip needs as many values"):
        farm.combinations({"a": ["1", "2"], "b": ["x"]}, "zip")
    assert [farm.toml_text(v) for v in (1e-4, 3, True, "nod", (0, 0, -9.8))] == [
        "0.0001", "3", "true", '"nod"', "[0, 0, -9.8]"]


def _kill_worker_once(marker: str, task):
    """The first attempt of variant 0 kills its own worker process once the run has written a frame: the run's
    working folder, its lock and its checkpoint stay behind, as after a crash."""
    if task.index == 0 and not os.path.exists(marker):
        root = Path(task.folder) / f"{task.name}.partial" / f"{task.name}.usdc"

        def kill_after_the_first_frame():
            while not root.exists():
                time.sleep(0.005)
            Path(marker).write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)

        threading.Thread(target=kill_after_the_first_frame, daemon=True).start()
    return farm.run_task(task)


def _kill_worker_always(task):
    os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.slow  # 4 s: Dask's retries; the faulting variant and the rerun stay in the default run
def test_a_killed_worker_is_retried_elsewhere_and_the_wedge_completes(tmp_path):
    marker = tmp_path / "killed.pid"
    out = tmp_path / "w"
    frames = 40  # long enough for the killer to see the first frame while the run goes on
    tasks = farm.wedge_tasks(TINY, {"strands.bend_stiffness": ["1e-4", "1e-3"]}, out,
                             overrides=[f"sim.frames={frames}"])
    records = farm.run_tasks(tasks, out, workers=2, sheet=False,
                             task_fn=functools.partial(_kill_worker_once, str(marker)))
    assert marker.is_file()  # the first attempt did die, mid-run
    assert [r["status"] for r in records] == ["ok", "ok"]
    assert records[0]["frames"] == frames and records[0]["worker"] is not None
    assert int(marker.read_text()) != os.getpid()
    arrays = _usd_arrays(records[0]["cache"])  # the retry wrote a whole cache over what the dead one left
    assert ("/World/Hair/guides", "points", float(frames)) in arrays
    assert not (out / tasks[0].name / f"{tasks[0].name}.partial").exists()


@pytest.mark.slow  # 4 s
def test_a_task_that_kills_every_worker_is_lost_after_bounded_retries(tmp_path):
    out = tmp_path / "w"
    tasks = farm.wedge_tasks(TINY, {"strands.bend_stiffness": ["1e-4"]}, out, overrides=FIXED)
    t0 = time.perf_counter()
    records = farm.run_tasks(tasks, out, workers=1, sheet=False, task_fn=_kill_worker_always)
    assert records[0]["status"] == "lost" and "died" in records[0]["message"]
    assert not (out / tasks[0].name / farm.MARKER).exists()  # a lost task runs again next time
    assert time.perf_counter() - t0 < 120


def test_a_faulting_variant_is_reported_and_the_rest_complete(tmp_path, capsys):
    out = tmp_path / "w"
    # no joint of tiny.toml may turn 1e-4 rad in a step: those variants stop on a SimulationFault at frame 1
    rc = main(["wedge", str(TINY), "-w", "sim.max_rotation_per_step=1.0,1e-4", "-w", "strands.drag=0.01,0.02",
               "--frames", str(FRAMES), "--workers", "2", "-o", str(out)])
    captured = capsys.readouterr()
    assert rc == 3
    records = json.loads((out / "summary.json").read_text())
    assert [r["status"] for r in records] == ["ok", "ok", "fault", "fault"]
    for r in records[2:]:
        assert r["message"].startswith("simulation fault at frame 1")
        assert "joint bent more than 0.0001 rad" in r["message"]
        assert f"fault    {r['name']}: simulation fault" in captured.out
        assert (out / r["name"] / farm.MARKER).is_file()  # a fault is a result: complete, not rerun
        # the frames before the fault (frame 0) stay readable where the run left them
        assert ".partial" in r["cache"] and ("/World/Hair/guides", "points", 0.0) in _usd_arrays(r["cache"])
        assert r["tip_travel_mean_m"] == 0.0
    assert all(r["frames"] == FRAMES for r in records[:2])
    assert "2 ok, 2 fault" in captured.out and (out / "sheet.png").is_file()
    md = (out / "summary.md").read_text()
    assert "fault" in md and "joint bent more than" in md


def test_batch_runs_shots_from_a_list_file(tmp_path):
    shots = tmp_path / "shots"
    shots.mkdir()
    for name in ("a", "b"):
        (shots / f"{name}.toml").write_text(TINY.read_text().replace('name = "tiny"', f'name = "shot_{name}"'))
    (tmp_path / "list.txt").write_text("# two shots\nshots/a.toml\nshots/b.toml  # the second\n")
    import hairwarp as hw

    records = hw.batch([f"@{tmp_path / 'list.txt'}"], out=tmp_path / "b", overrides=["sim.frames=2"], workers=2)
    assert [r["name"] for r in records] == ["shot_a_0", "shot_b_1"]
    assert [r["status"] for r in records] == ["ok", "ok"] and all(r["frames"] == 2 for r in records)
    assert (tmp_path / "b" / "sheet.png").is_file() and (tmp_path / "b" / "summary.csv").is_file()


def test_bad_wedge_keys_and_unequal_zip_exit_2_with_one_line(tmp_path, capsys):
    out = tmp_path / "never"
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"\xff\xfe\x00bin")  # a list of scenes that is no text: named, not the codec's message alone
    assert main(["batch", f"@{binary}", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{binary}: is no list of scenes (not UTF-8 text" in err[0], err
    assert main(["wedge", str(TINY), "-w", "strands.bend_stiffness=1e-4,1e-3", "-w", "strands.stifness=1,2",
                 "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "strands.stifness" in err[0] and "unknown key" in err[0]
    assert main(["wedge", str(TINY), "-w", "strands.bend_stiffness=1e-4,-1", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "strands.bend_stiffness" in err[0]
    assert main(["wedge", str(TINY), "-w", "strands.bend_stiffness=1e-4,1e-3", "-w", "strands.drag=0.01",
                 "--zip", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--zip" in err[0]
    # a wedged key also fixed for every run: the wedge's values used to win without a word
    assert main(["wedge", str(TINY), "-w", "sim.substeps=2,4", "-s", "sim.substeps=8", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sim.substeps" in err[0] and "-s sim.substeps=8" in err[0]
    assert main(["wedge", str(TINY), "-w", "sim.frames=2,4", "--frames", "3", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sim.frames" in err[0] and "--frames" in err[0]
    # a wedged key of a section the scene switches off (tiny has no links): every variant would run the same
    assert main(["wedge", str(TINY), "-w", "links.damping=0.001,0.05", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["hairwarp: -w links.damping: links.enabled is false in this scene, so this changes nothing; set "
                   "links.enabled too"], err
    assert not out.exists()  # nothing was submitted


@pytest.mark.parametrize("command", ["wedge", "batch"])
def test_an_output_that_cannot_be_a_folder_exits_2_with_one_line(tmp_path, capsys, command):
    """The output of a wedge or a batch is a folder: an existing file there (a cache, as ``hairwarp run -o`` names
    it) and a folder the system cannot create (here under that file) are one line naming the path, exit 2, before any
    run starts; both were the traceback of ``mkdir``, exit 1."""
    cache = tmp_path / "tiny.usdc"
    cache.write_bytes(b"not a folder")
    args = [command, str(TINY)] + (["-w", "strands.drag=0.01"] if command == "wedge" else []) + ["--workers", "1"]
    assert main([*args, "-o", str(cache)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{cache} is a file" in err[0] and f"such as {tmp_path / 'tiny'}" in err[0], err
    assert main([*args, "-o", str(cache / "w")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"hairwarp: cannot create the output folder {cache / 'w'} (Not a directory): name a folder this "
                   f"user can create and write"]
    assert cache.read_bytes() == b"not a folder" and sorted(tmp_path.iterdir()) == [cache]


def test_sheet_rows_name_the_wedged_keys_in_full():
    """``strands.damping`` and ``links.damping`` wedged together: each row names its keys in full (both were
    ``damping = ...``)."""
    record = {"name": "tiny_0", "values": {"strands.damping": 1e-7, "links.damping": 0.002}, "status": "ok"}
    assert farm._row_title(record).splitlines() == ["tiny_0", "strands.damping = 1e-07", "links.damping = 0.002",
                                                     "ok"]


@pytest.mark.parametrize("command", ["wedge", "batch"])
def test_one_run_is_counted_in_the_singular(tmp_path, capsys, monkeypatch, command):
    """The line a wedge or batch starts with: '1 variant', '1 shot' (was '1 variants', '1 shots')."""

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(farm, "run_tasks", stop)
    args = [command, str(TINY)] + (["-w", "strands.drag=0.01"] if command == "wedge" else [])
    assert main([*args, "-o", str(tmp_path / "w")]) == 130
    first = capsys.readouterr().err.splitlines()[0]
    assert first == {"wedge": f"wedge    1 variant of {TINY} into {tmp_path / 'w'}",
                     "batch": f"batch    1 shot into {tmp_path / 'w'}"}[command]


def test_missing_dask_gives_the_install_command(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["wedge", str(TINY), "-w", "strands.drag=0.01,0.02", "-o", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'pip install "dask[distributed]' in err[0]


def test_ctrl_c_cancels_closes_the_cluster_and_exits_130(tmp_path):
    out, err_path = tmp_path / "w", tmp_path / "stderr.txt"
    cmd = [sys.executable, "-m", "hairwarp", "wedge", str(TINY), "-w", "strands.bend_stiffness=1e-3,2e-3,3e-3",
           "--frames", "100000", "--workers", "2", "-o", str(out)]
    with open(err_path, "w") as err:
        # Ctrl-C as a terminal's foreground job gets it: a shell starts background jobs with SIGINT ignored, which
        # their children inherit, and Python then raises no KeyboardInterrupt
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + CLI_TIMEOUT_S
        while "2 running" not in err_path.read_text() and time.monotonic() < deadline and p.poll() is None:
            time.sleep(0.2)
        os.killpg(p.pid, signal.SIGINT)  # what the terminal does on Ctrl-C: the whole process group
        rc = p.wait(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = err_path.read_text()
    assert rc == 130, text
    assert "Traceback" not in text and text.count("interrupted") == 1, text
    assert text.strip().splitlines()[-1].startswith("hairwarp: interrupted")
    ps = subprocess.run(["ps", "-o", "stat=,args=", "-g", str(p.pid)], capture_output=True, text=True).stdout
    assert not [line for line in ps.splitlines() if "spawn_main" in line and not line.startswith("Z")], ps
    complete = [t for t in os.listdir(out) if (out / t / farm.MARKER).exists()]
    assert not complete, (complete, text)  # the interrupted runs are partial: a rerun redoes them


def test_help_lists_wedge_and_batch(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "wedge" in text and "batch" in text
    with pytest.raises(SystemExit):
        main(["wedge", "--help"])
    text = capsys.readouterr().out
    assert "--scheduler" in text and "--zip" in text and "--workers" in text


def test_threads_per_run_fills_the_cores_without_oversubscribing():
    assert farm.threads_per_run(16, 4) == 4 and farm.threads_per_run(2, 2) == 1 and farm.threads_per_run(2, 3) == 1
    assert farm.local_cores() == len(os.sched_getaffinity(0))


def test_engine_overhead_from_task_timestamps():
    from hairwarp.benchmarks.wedge import _overheads

    def rec(name, worker, submit, start, end, received):
        return {"name": name, "worker": worker, "timing": {"t_submit": submit, "t_start": start, "t_end": end,
                                                           "t_received": received, "simulate_s": end - start - 0.1}}

    rows = {r["name"]: r for r in _overheads([rec("a", "w1", 0.0, 0.5, 3.0, 3.02), rec("b", "w1", 0.0, 3.05, 5.0, 5.5),
                                              rec("c", "w2", 1.0, 1.25, 2.0, 2.01)])}
    assert rows["a"]["scheduling_s"] == pytest.approx(0.5) and rows["a"]["transfer_s"] == pytest.approx(0.02)
    assert rows["b"]["scheduling_s"] == pytest.approx(0.05) and rows["b"]["transfer_s"] == pytest.approx(0.5)
    assert rows["c"]["scheduling_s"] == pytest.approx(0.25) and rows["b"]["task_s"] == pytest.approx(1.95)


def test_a_run_that_sets_its_threads_keeps_them_on_a_local_worker(tmp_path, monkeypatch):
    # A local worker runs each task on its share of the cores, unless the task names its own thread count.
    monkeypatch.setattr(farm, "_WORKER_THREADS", 2)
    own, share = farm.wedge_tasks(TINY, {"sim.threads": ["1"], "sim.frames": ["1"]}, tmp_path / "own")[0], \
        farm.wedge_tasks(TINY, {"sim.frames": ["1"]}, tmp_path / "share")[0]
    for task, expected in ((own, 1), (share, 2)):
        record = farm.run_task(task)
        assert record["status"] == "ok", record
        written = json.loads((Path(task.folder) / farm.SCENE_JSON).read_text())
        assert written["scene"]["sim"]["threads"] == expected, (task.overrides, written["scene"]["sim"])


def test_wedge_summary_lists_each_runs_notes(tmp_path):
    """A run's notes (frames taken again after a fault, ...) follow the summary's table, named by run; a run
    without notes adds no line."""
    from hairwarp.farm import write_summary

    base = {"status": "ok", "frames": 10, "frames_planned": 10, "seconds": 1.0, "broken_links": None,
            "contacts_mean": None, "contacts_max": None, "tip_travel_mean_m": 0.1, "tip_travel_max_m": 0.2,
            "message": None}
    note = "3 frames faulted at 2 substeps and were taken again in more steps: frame 1 in 4 steps (x)"
    records = [{**base, "index": 0, "name": "calm", "values": {"wind.velocity": [0.0, 0.0, 0.0]}, "notes": []},
               {**base, "index": 1, "name": "windy", "values": {"wind.velocity": [500.0, 0.0, 0.0]},
                "notes": [note]}]
    _, md_path, _ = write_summary(records, tmp_path)
    md = md_path.read_text()
    assert f"- **windy**: {note}" in md and "- **calm**" not in md
    assert md.index("Notes of the runs:") > md.index("| 1 | windy |")


def test_local_workers_run_with_the_farms_dask_settings():
    # The settings that keep Dask's housekeeping off the runs' cores reach the worker processes, not only the
    # process that starts the cluster.
    import dask

    cluster = farm._Cluster(None, 1, 1, lambda message: None)
    try:
        seen = cluster.client.run(lambda: {k: dask.config.get(k) for k in farm.LOCAL_CLUSTER_CONFIG})
    finally:
        cluster.close()
    assert seen and all(v == farm.LOCAL_CLUSTER_CONFIG for v in seen.values()), seen
