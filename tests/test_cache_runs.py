"""Runs that stop, fail or share an output: real ``hairwarp run`` children of scenes/tiny.toml, read back with
usd-core and compared against an uninterrupted run."""

import contextlib
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

TINY = Path(__file__).resolve().parents[1] / "scenes" / "tiny.toml"


def _run(out, *extra, wait=True):
    cmd = [sys.executable, "-m", "hairwarp", "run", str(TINY), "-o", str(out), "-s", "output.preview=false", *extra]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _samples(path) -> dict:
    """Every time sample of every attribute of a stage, read back by usd-core."""
    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            for t in attr.GetTimeSamples():
                out[(str(attr.GetPath()), t)] = np.asarray(attr.Get(t))
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run of 40 frames."""
    out = tmp_path_factory.mktemp("ref") / "tiny.usdc"
    res = _run(out, "--frames", "40", "-s", "sim.substeps=32")
    assert res.returncode == 0, res.stderr
    return _samples(out)


def _stop_at_random_frame(out, sig, seed):
    proc = _run(out, "--frames", "40", "-s", "sim.substeps=32", wait=False)
    rng = np.random.default_rng(seed)
    target = int(rng.integers(2, 12))
    root = out.with_name("tiny.partial") / "tiny.usdc"
    deadline = time.time() + 60
    while time.time() < deadline:  # wait until that many frames are complete
        if root.exists():
            try:
                last = Usd.Stage.Open(str(root)).GetEndTimeCode()
            except Exception:
                last = -1
            if last >= target:
                break
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), pytest.param(signal.SIGINT, 130, marks=pytest.mark.slow),
                                       pytest.param(signal.SIGHUP, 129, marks=pytest.mark.slow), (signal.SIGKILL, -9)])
def test_stop_keeps_every_frame_and_resume_equals_an_uninterrupted_run(tmp_path, reference, sig, code):
    out = tmp_path / "tiny.usdc"
    rc, err = _stop_at_random_frame(out, sig, seed=int(sig))
    assert rc == code, err
    partial = tmp_path / "tiny.partial" / "tiny.usdc"
    assert not out.exists() and partial.exists()
    if sig != signal.SIGKILL:
        assert "Traceback" not in err and f"stopped by {signal.Signals(sig).name}" in err
        assert str(partial) in err
    # every complete frame is readable and equals the uninterrupted run's
    kept = _samples(partial)
    assert kept and all(np.array_equal(v, reference[k]) for k, v in kept.items())
    assert not [p for p in tmp_path.rglob(".*")], "hidden leftovers"
    res = _run(out, "--frames", "40", "-s", "sim.substeps=32", "--resume")
    assert res.returncode == 0, res.stderr
    assert "resuming after frame" in res.stderr
    resumed = _samples(out)
    assert resumed.keys() == reference.keys()
    for key, value in reference.items():
        np.testing.assert_array_equal(resumed[key], value, err_msg=str(key))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.clips", "tiny.usdc"]


def test_a_failing_run_keeps_the_previous_cache(tmp_path):
    out = tmp_path / "tiny.usdc"
    assert _run(out, "--frames", "3").returncode == 0
    before = _samples(out)
    res = _run(out, "--frames", "10", "-s", 'sim.integrator="semi_implicit"', "-s", "strands.bend_stiffness=10.0",
               "-s", "sim.substeps=1")
    assert res.returncode == 3 and "simulation fault" in res.stderr and "Traceback" not in res.stderr
    assert str(tmp_path / "tiny.partial" / "tiny.usdc") in res.stderr
    after = _samples(out)
    assert after.keys() == before.keys() and all(np.array_equal(after[k], v) for k, v in before.items())


def test_resume_refuses_a_cache_that_would_not_fit_and_takes_a_changed_simulation(tmp_path, capsys):
    """A run that faulted (explicit stiff springs at one step a frame) leaves its frames; ``hairwarp info`` and
    ``preview`` of the cache it did not write name where they are; a resume with another dense
    hair count is refused (its curves would change between frames) and leaves them, a resume at more substeps with
    the implicit integrator goes on from the last good frame and says what changed (through the API, as
    ``hairwarp run --resume`` calls it; the command's exit codes are checked above)."""
    import hairwarp as hw
    from hairwarp.cli import main
    from hairwarp.runner import simulate

    out = tmp_path / "tiny.usdc"
    tiny = hw.Scene.load(TINY, ["output.preview=false", "strands.bend_stiffness=10.0"])
    stiff = tiny.with_overrides(['sim.integrator="semi_implicit"', "sim.substeps=1"])
    with pytest.raises(hw.SimulationFault):
        simulate(stiff, out, frames=6, progress=False)
    partial = tmp_path / "tiny.partial" / "tiny.usdc"
    kept = _samples(partial)
    capsys.readouterr()
    for command in (["info", str(out)], ["preview", str(out), "-o", str(tmp_path / "p.png")]):
        assert main(command) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "no such file" in err and f"frames in {partial.resolve()}" in err, err
    last = int(max(t for _, t in kept))
    assert main(["info", str(partial)]) == 0
    assert f"frames 0 .. {last}: {last + 1} time samples" in capsys.readouterr().out
    with pytest.raises(ValueError, match=r"cannot resume: .*dense.count \(20, was 0\)"):
        simulate(stiff.with_overrides(["dense.count=20"]), out, frames=6, progress=False, resume=True)
    assert not out.exists() and _samples(partial).keys() == kept.keys()
    result = simulate(tiny.with_overrides(["sim.substeps=16"]), out, frames=6, progress=False, resume=True)
    assert any("resuming with a changed simulation" in n and "sim.integrator" in n for n in result.notes)
    stage = Usd.Stage.Open(str(out))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 6.0)


def test_a_second_run_on_the_same_output_is_refused(tmp_path):
    out = tmp_path / "tiny.usdc"
    first = _run(out, "--frames", "200", "-s", "sim.substeps=64", wait=False)
    root = tmp_path / "tiny.partial" / "tiny.usdc"
    deadline = time.time() + 60
    while not root.exists() and time.time() < deadline:
        time.sleep(0.05)
    second = _run(out, "--frames", "2")
    first.kill()  # its lock stays behind
    # not reaped yet: a zombie answers signal 0 as a live process does (its parent, this test, has not waited, as
    # when a killed run's parent is gone and the system's first process reaps it late)
    stat = Path(f"/proc/{first.pid}/stat")
    while stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] not in "ZX" and time.time() < deadline:
        time.sleep(0.01)
    assert (tmp_path / "tiny.partial" / "lock").exists()
    assert second.returncode == 2 and "another run" in second.stderr and "Traceback" not in second.stderr
    # the lock of a killed run does not stop the next one, which says what it found
    res = _run(out, "--frames", "2")
    first.communicate(timeout=60)
    assert res.returncode == 0 and "did not finish" in res.stderr, res.stderr


@pytest.mark.parametrize("args, match", [
    (["-o", "{d}/x.txt"], "must end in"),
    (["-o", "{d}"], "is a folder"),
    (["--device", "cuda"], "no CUDA device"),
    (["-s", "groom.count=10000000"], "memory"),
    (["-s", "dense.count=100000000"], "memory"),
    (["-s", "sim.gravity=[0, 0, -inf]"], "sim.gravity"),
])
def test_checks_before_the_first_step(tmp_path, args, match):
    if args[0] == "--device" and "cuda" in args[1]:
        import warp as wp

        if wp.is_cuda_available():
            pytest.skip("this machine has CUDA")
    args = [a.format(d=tmp_path) for a in args]
    out = tmp_path / "ok.usdc"
    cmd = [sys.executable, "-m", "hairwarp", "run", str(TINY), "-s", "output.preview=false"]
    cmd += args if args[0] == "-o" else ["-o", str(out), *args]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and match in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert "pxrInternal" not in res.stderr


def test_read_only_and_immutable_folders(tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not supported here")
    try:
        res = _run(folder / "tiny.usdc", "--frames", "2")
    finally:
        subprocess.run(["chattr", "-i", str(folder)])
    assert res.returncode == 2 and "cannot write" in res.stderr and "Traceback" not in res.stderr


def _message_lines(res) -> int:
    """Lines hairwarp wrote on stderr (Warp may print a CUDA-driver warning of its own as it loads)."""
    return sum(1 for line in res.stderr.splitlines() if line.startswith("hairwarp:"))


@contextlib.contextmanager
def _tmpfs(folder: Path, options: str):
    """A tmpfs mounted at ``folder`` for the test, or a skip saying why it cannot be."""
    folder.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"this system does not allow mounting a tmpfs: {res.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True)


def test_disk_too_small_for_the_estimate_is_refused_before_the_first_step(tmp_path):
    with _tmpfs(tmp_path / "small", "size=160k") as mnt:
        res = _run(mnt / "tiny.usdc", "--frames", "100000")
        assert res.returncode == 2, res.stderr
        assert "are free on its disk" in res.stderr and _message_lines(res) == 1, res.stderr
        assert not (mnt / "tiny.partial").exists() and not (mnt / "tiny.usdc").exists()


def test_disk_full_mid_run_keeps_frames_and_exits_3(tmp_path):
    """The pre-check is bypassed (its estimate would refuse the run), so the disk fills at a later frame for sure."""
    with _tmpfs(tmp_path / "small", "size=256k") as mnt:
        out = mnt / "tiny.usdc"
        code = ("import sys\nimport hairwarp.runner as r\nr._check_disk_space = lambda *a, **k: None\n"
                "from hairwarp.cli import main\nsys.exit(main(sys.argv[1:]))")
        cmd = [sys.executable, "-c", code, "run", str(TINY), "-o", str(out), "-s", "output.preview=false",
               "-s", "output.guides=true", "--frames", "100000"]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        partial = mnt / "tiny.partial" / "tiny.usdc"
        assert res.returncode == 3, res.stderr
        assert "Traceback" not in res.stderr and "pxrInternal" not in res.stderr
        assert "no space left" in res.stderr and str(partial) in res.stderr, res.stderr
        assert not out.exists()
        samples = _samples(partial)  # usd-core reads every frame the run kept
        assert samples, res.stderr


def test_read_only_file_system_is_refused_before_the_first_step(tmp_path):
    with _tmpfs(tmp_path / "ro", "ro,size=1m") as mnt:
        res = _run(mnt / "tiny.usdc", "--frames", "2")
        assert res.returncode == 2, res.stderr
        assert "cannot write" in res.stderr and str(mnt) in res.stderr, res.stderr
        assert "Traceback" not in res.stderr and _message_lines(res) == 1, res.stderr


@pytest.mark.parametrize("frames", [10, 100, pytest.param(1000, marks=pytest.mark.slow)])
def test_cache_size_is_linear_in_its_frames(tmp_path, frames):
    out = tmp_path / "tiny.usdc"
    res = _run(out, "--frames", str(frames), "-s", "sim.substeps=1")
    assert res.returncode == 0, res.stderr
    size = out.stat().st_size + sum(p.stat().st_size for p in (tmp_path / "tiny.clips").iterdir())
    flat = tmp_path / "flat.usdc"
    Usd.Stage.Open(str(out)).Export(str(flat))
    assert size <= 1.1 * flat.stat().st_size, (size, flat.stat().st_size)


def test_a_stop_while_drawing_the_preview_keeps_the_complete_cache(tmp_path, monkeypatch):
    """A signal after the last frame, while the preview is drawn: the cache is complete and in place, and the run
    reports the stop (RunStopped, exit 128 + signal) instead of dying mid-picture; ``--resume`` then draws the
    picture from the cache instead of saying there is nothing to resume."""
    from PIL import Image

    import hairwarp as hw
    import hairwarp.preview
    from hairwarp.runner import RunStopped, simulate

    def render_and_get_stopped(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(hairwarp.preview, "render_frames", render_and_get_stopped)
    scene = hw.Scene.load(TINY, overrides=["sim.frames=3"])
    out = tmp_path / "tiny.usdc"
    with pytest.raises(RunStopped, match="while drawing the preview") as info:
        simulate(scene, out, progress=False)
    assert info.value.signum == signal.SIGTERM
    assert "hairwarp run --resume draws it from the cache" in str(info.value)
    stage = Usd.Stage.Open(str(out))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 3.0)
    del stage
    picture = out.with_suffix(".png")
    assert not picture.exists()

    # --resume draws the missing picture from the cache, simulating nothing and leaving the cache as it was; then,
    # with the picture there, it has nothing to do
    monkeypatch.undo()
    before = _samples(out)
    with pytest.raises(ValueError, match="is complete: nothing to resume"):  # more frames than it holds: no picture
        simulate(scene, out, frames=5, progress=False, resume=True)
    assert not picture.exists()
    result = simulate(scene, out, progress=False, resume=True)
    assert (result.frames, result.resumed_frames, result.preview_path) == (3, 3, picture)
    assert any("missing preview was drawn" in note for note in result.notes)
    with Image.open(picture) as image:
        assert image.size[0] > 100 and image.size[1] > 100
    after = _samples(out)
    assert before.keys() == after.keys() and all(np.array_equal(before[k], after[k]) for k in before)
    with pytest.raises(ValueError, match="is complete: nothing to resume"):
        simulate(scene, out, progress=False, resume=True)


def test_resume_with_nothing_stopped_says_why(tmp_path, capsys):
    """``--resume`` where no run stopped, and where the run finished: each says so, not that a folder which does not
    exist "holds no complete frame"."""
    from hairwarp.cli import main

    out = tmp_path / "tiny.usdc"
    args = ["run", str(TINY), "-o", str(out), "-s", "output.preview=false", "--frames", "1"]
    assert main([*args, "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"no stopped run to resume at {out}" in err and "holds no complete frame" not in err, err
    assert main(args) == 0
    capsys.readouterr()
    assert main([*args, "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"the cache {out} is complete: nothing to resume" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.clips", "tiny.usdc"]


def test_a_run_refuses_to_replace_what_is_not_its_cache(tmp_path, capsys):
    """A cache of the same name with another suffix keeps its frames in the same ``<stem>.clips``: a run of
    ``k.usda`` beside ``k.usdc`` would replace them (``k.usdc`` then no longer opened). A ``<stem>.clips`` or
    ``<stem>.partial`` that hairwarp did not write (a file, or a folder with other files) is refused too, and left as
    it is; the same output again replaces its own cache."""
    from hairwarp.cli import main

    def run(name):
        return main(["run", str(TINY), "-o", str(tmp_path / name), "-s", "output.preview=false", "--frames", "2"])

    assert run("k.usdc") == 0
    before = _samples(tmp_path / "k.usdc")
    capsys.readouterr()
    assert run("k.usda") == 2
    err = capsys.readouterr().err
    assert f"the cache {tmp_path / 'k.usdc'} keeps its frames in {tmp_path / 'k.clips'}" in err and len(
        err.strip().splitlines()) == 1, err
    after = _samples(tmp_path / "k.usdc")
    assert after.keys() == before.keys() and not (tmp_path / "k.usda").exists()
    for key, value in before.items():
        np.testing.assert_array_equal(after[key], value, err_msg=str(key))
    assert run("k.usdc") == 0  # its own cache again
    (tmp_path / "y.clips").write_text("notes")
    (tmp_path / "w.partial").mkdir()
    (tmp_path / "w.partial" / "junk").write_text("mine")
    capsys.readouterr()
    assert run("y.usdc") == 2 and "y.clips is a file" in capsys.readouterr().err
    assert run("w.usdc") == 2 and "did not write (junk)" in capsys.readouterr().err
    assert (tmp_path / "y.clips").read_text() == "notes" and (tmp_path / "w.partial" / "junk").read_text() == "mine"


def test_summary_counts_the_frames_this_run_simulated(tmp_path, capsys, monkeypatch):
    """A resumed run's last line counts the frames it simulated and those the stopped run had, in the singular for
    one (a run of 6 frames resumed after frame 4 simulated 2, not 6)."""
    from hairwarp import runner
    from hairwarp.cli import main

    out = tmp_path / "tiny.usdc"
    args = ["run", str(TINY), "-o", str(out), "-s", "output.preview=false", "--frames"]
    assert main([*args, "1"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("1 frame simulated in ")
    frame_stats = runner.Simulation.frame_stats
    seen = []

    def stop_at_frame_4(sim):  # a SIGTERM while frame 4 is written: the run stops after it
        seen.append(len(seen))
        if seen[-1] == 4:
            os.kill(os.getpid(), signal.SIGTERM)
        return frame_stats(sim)

    monkeypatch.setattr(runner.Simulation, "frame_stats", stop_at_frame_4)
    assert main([*args, "6"]) == 128 + signal.SIGTERM
    assert "stopped by SIGTERM after frame 4" in capsys.readouterr().err
    monkeypatch.setattr(runner.Simulation, "frame_stats", frame_stats)
    assert main([*args, "6", "--resume"]) == 0
    summary = capsys.readouterr().out.splitlines()[-1]
    assert summary.startswith("2 frames simulated after the 4 frames of the stopped run in "), summary
    # the frames' time apart from the set-up's: the frames alone, per frame, then the whole call
    frame_s, per_frame, total = map(float, re.search(r"in ([\d.]+) s \(([\d.e-]+) s a frame\); ([\d.]+) s in all",
                                                     summary).groups())
    # the line prints the frames' seconds to 0.01 s and the per-frame figure to 3 digits: within 0.01 s or 1 %
    assert per_frame == pytest.approx(frame_s / 2, rel=0.01, abs=0.01) and frame_s < total


@pytest.mark.parametrize("where, sig, said", [
    ("hairwarp.scene:Scene.load", signal.SIGHUP, "stopped by SIGHUP before the run began; nothing was written"),
    ("hairwarp.runner:Simulation.__init__", signal.SIGTERM, "stopped by SIGTERM before frame 0. No frame was complete"),
])
def test_a_stop_before_the_first_frame_is_one_line_and_releases_the_lock(tmp_path, where, sig, said):
    """SIGTERM and SIGHUP while the run starts (the scene is read; the simulation is built, with the lock taken)
    end it with one line and 128 + signal, as SIGINT does; they used to end the process silently, the lock left."""
    module, attr = where.split(":")
    owner, name = attr.split(".")
    code = textwrap.dedent(f"""
        import os, sys
        import {module} as m
        from hairwarp.cli import main

        original = m.{owner}.{name}
        def stopped(*args, **kwargs):
            os.kill(os.getpid(), {int(sig)})
            return original(*args, **kwargs)
        m.{owner}.{name} = stopped
        sys.exit(main(sys.argv[1:]))
    """)
    out = tmp_path / "tiny.usdc"
    res = subprocess.run([sys.executable, "-c", code, "run", str(TINY), "-o", str(out), "--frames", "2"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 128 + sig, res.stderr
    assert said in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert list(tmp_path.iterdir()) == [], "the lock or a frame left behind"


def test_the_lock_is_held_until_the_preview_is_written(tmp_path, monkeypatch, capsys):
    """A second run on the output while the first draws its preview is refused, as while it simulates: the lock
    went with the cache's move into place, and the second run's cache ended beside the first run's preview."""
    import hairwarp.preview
    from hairwarp.cli import main

    out = tmp_path / "tiny.usdc"
    render_frames = hairwarp.preview.render_frames
    second = []

    def render_while_a_second_run_starts(*args, **kwargs):
        second.append(main(["run", str(TINY), "-o", str(out), "--frames", "1", "-s", "output.preview=false"]))
        return render_frames(*args, **kwargs)

    monkeypatch.setattr(hairwarp.preview, "render_frames", render_while_a_second_run_starts)
    assert main(["run", str(TINY), "-o", str(out), "--frames", "2"]) == 0
    assert second == [2] and "another run" in capsys.readouterr().err
    assert Usd.Stage.Open(str(out)).GetEndTimeCode() == 2.0, "the first run's cache"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.clips", "tiny.png", "tiny.usdc"]


def test_disk_too_small_for_the_topology_state_and_preview_is_refused_before_the_first_step(tmp_path, capsys):
    """tiny's frames fit in 100 KiB, its topology layer, stored state and preview do not: the check counted the frames
    alone (40.6 KiB), passed, and the run failed at frame 0 with exit 3."""
    from hairwarp.cli import main

    with _tmpfs(tmp_path / "small", "size=100k") as mnt:
        assert main(["run", str(TINY), "-o", str(mnt / "tiny.usdc")]) == 2
        err = capsys.readouterr().err
        assert "are free on its disk" in err and "topology" in err and "preview" in err, err
        assert list(mnt.iterdir()) == []


def test_a_full_disk_at_the_preview_keeps_the_complete_cache_and_exits_3(tmp_path, capsys, monkeypatch):
    """The disk fills while the preview is written (the check before the run is bypassed: it would refuse it): the
    run says its cache is complete and its preview missing, exits 3, and leaves no picture; ``hairwarp preview`` on
    that disk too, for a PNG and a GIF (which it left truncated, with a traceback)."""
    from hairwarp import runner
    from hairwarp.cli import main

    monkeypatch.setattr(runner, "_check_disk_space", lambda *args, **kwargs: None)
    # the cache takes 88 KiB in the disk's 4 KiB blocks; a sheet of 8 frames 345 KiB, the GIF 348 KiB
    with _tmpfs(tmp_path / "small", "size=300k") as mnt:
        out = mnt / "tiny.usdc"
        assert main(["run", str(TINY), "-o", str(out), "-s", "output.preview_frames=8"]) == 3
        err = capsys.readouterr().err
        assert f"the cache {out} is complete (11 frames), the preview is missing: no space left on {mnt}" in err, err
        assert "Traceback" not in err
        assert sorted(p.name for p in mnt.iterdir()) == ["tiny.clips", "tiny.usdc"]
        assert Usd.Stage.Open(str(out)).GetEndTimeCode() == 10.0
        for extra in (["--frames", "8"], ["--gif"]):
            picture = mnt / ("x.gif" if "--gif" in extra else "x.png")
            assert main(["preview", str(out), "-o", str(picture), *extra]) == 3
            err = capsys.readouterr().err
            assert f"no space left on {mnt} for the picture {picture}: it needs" in err, err
            assert sorted(p.name for p in mnt.iterdir()) == ["tiny.clips", "tiny.usdc"]


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_the_disk_check_counts_at_least_what_the_cache_takes(tmp_path, monkeypatch, suffix):
    """The disk-space check's frames and topology cover what the cache holds when the run ends, in binary and in
    text (a ``.usda`` frame of the default scene took 3.4 times the binary estimate, and a run the check let start
    could fill the disk). Above the measure by at most 2.5x, so the check does not refuse runs that fit."""
    from hairwarp import runner
    from hairwarp.cli import main

    counted = {}
    needed = runner._disk_needed

    def record(*args, **kwargs):
        counted.update(needed(*args, **kwargs))
        return counted

    monkeypatch.setattr(runner, "_disk_needed", record)
    out = tmp_path / f"k{suffix}"
    scene = Path(__file__).resolve().parents[1] / "scenes" / "long_hair.toml"
    assert main(["run", str(scene), "-o", str(out), "--frames", "3", "-s", "output.preview=false"]) == 0
    written = out.stat().st_size + sum(p.stat().st_size for p in out.with_suffix(".clips").rglob("*") if p.is_file())
    estimate = counted["frames"] + counted["topology"]
    assert written <= estimate <= 2.5 * written, (written, counted)


def test_the_disk_check_counts_a_groom_files_guides_and_dense_hair_by_density(tmp_path, monkeypatch):
    """The frames' share of the disk check comes from the built run: guides read from a groom file and dense hair
    asked for by ``dense.density`` have their counts only there (the Ratboy mohawk's 444 guides were counted as none,
    2 KiB a frame against the 183 KiB written). As above: the frames and topology counted cover the cache, and lie
    above it by at most 2.5x."""
    from hairwarp import runner
    from hairwarp.cli import main
    from hairwarp.groom import scalp_groom
    from hairwarp.io.cem_hair import write_hair

    write_hair(tmp_path / "g.hair", scalp_groom(count=200, length=0.25, points=13, seed=3))
    scene = tmp_path / "s.toml"
    scene.write_text('[sim]\nframes = 3\nsegments = 12\n[groom]\nfile = "g.hair"\n[head]\nshape = "none"\n'
                     "[dense]\ndensity = 4e4\n[output]\npreview = false\n")
    counted = {}
    needed = runner._disk_needed
    monkeypatch.setattr(runner, "_disk_needed", lambda *a, **k: counted.update(needed(*a, **k)) or counted)
    out = tmp_path / "k.usdc"
    assert main(["run", str(scene), "-o", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    dense = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/hair"))
    assert dense and len(dense.GetCurveVertexCountsAttr().Get()) > 1000  # the density asked for dense hair
    written = out.stat().st_size + sum(p.stat().st_size for p in out.with_suffix(".clips").rglob("*") if p.is_file())
    estimate = counted["frames"] + counted["topology"]
    assert written <= estimate <= 2.5 * written, (written, counted)
