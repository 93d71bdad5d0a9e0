"""The ``hairwarp`` command, run as ``python -m hairwarp`` in a subprocess (what a user types)."""

import importlib.util
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "scenes"
# Generous wall-clock bound on one CLI call that does not simulate (start-up, parse, describe).
CLI_TIMEOUT_S = 120


def _hairwarp(*args, cwd=None, env=None):
    return subprocess.run([sys.executable, "-m", "hairwarp", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=CLI_TIMEOUT_S)


def _has(module):
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def test_help_lists_the_subcommands():
    r = _hairwarp("--help")
    assert r.returncode == 0
    for cmd in ("run", "info", "bench", "preview"):
        assert cmd in r.stdout
    r = _hairwarp("run", "--help")
    assert r.returncode == 0 and "--frames" in r.stdout and "KEY=VALUE" in r.stdout
    # every suite that `hairwarp bench` accepts is named in its help (argparse wraps the lines)
    from hairwarp.bench import EXTRA_SUITES, SUITES

    r = _hairwarp("bench", "--help")
    assert r.returncode == 0
    text = " ".join(r.stdout.split())
    assert all(name in text for name in (*SUITES, *EXTRA_SUITES))


def test_version():
    import hairwarp

    r = _hairwarp("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"hairwarp {hairwarp.__version__}"


def test_usage_errors_exit_2():
    """Exit status 2 and one line naming the option, as every other error (argparse's usage block left out); a key
    set by -s and by its option too is refused (the option won, and the -s value went unchecked)."""
    for args, said in ((), "required: COMMAND"), (("fly",), "invalid choice: 'fly'"), \
            (("run", "--frames", "0"), "--frames: expected a positive integer"), \
            (("run", "--threads", "abc"), "--threads: expected an integer >= 0"), \
            (("wedge", "--workers", "0"), "--workers: expected a positive integer"), \
            (("run", "-o", ""), "--output: expected a path, got an empty one"), \
            (("run", "--frames", "3", "-s", 'sim.frames="abc"'), 'sim.frames is set twice, by -s sim.frames="abc"'), \
            (("info", "."), ".: is a folder; name a scene (.toml), a groom or a cache in it"):
        r = _hairwarp(*args)
        assert r.returncode == 2 and said in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_broken_scene_exits_2_and_names_the_key(tmp_path):
    scene = tmp_path / "broken.toml"
    scene.write_text(textwrap.dedent("""
        [groom]
        generator = "scalp"
        [head.motion]
        kind = "nod"
        perod = 1.0
        [sim]
        frames = -3
    """))
    for cmd in (("run", scene), ("info", scene)):
        r = _hairwarp(*cmd, cwd=tmp_path)
        assert r.returncode == 2, r.stderr
        assert "Traceback" not in r.stderr
        assert str(scene.resolve()) in r.stderr
        assert "head.motion.perod" in r.stderr and "did you mean 'period'" in r.stderr
        assert "sim.frames" in r.stderr
        assert not (tmp_path / "out").exists()


def test_bad_override_exits_2(tmp_path):
    r = _hairwarp("run", SCENES / "tiny.toml", "-s", "sim.integrator=verlet", cwd=tmp_path)
    assert r.returncode == 2 and "sim.integrator" in r.stderr and "Traceback" not in r.stderr


def test_dense_hair_past_memory_or_none_exits_2_naming_the_key(tmp_path, capsys):
    """A ``dense.density`` an extra zero or six too large is refused in one line naming the scene and the key, before
    anything of its size is allocated (1e10 strands/m^2 ran numpy out of memory with a traceback), and one that
    gives no strand too; nothing is written."""
    from hairwarp.cli import main

    for density, said in (("1e10", "that fit in memory"), ("1e-3", "none to build")):
        code = main(["run", str(SCENES / "tiny.toml"), "-o", str(tmp_path / "t.usdc"), "-s",
                     f"dense.density={density}"])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
        assert str(SCENES / "tiny.toml") in err and "dense.density" in err and said in err, err
        assert list(tmp_path.iterdir()) == []


def test_a_groom_file_past_memory_exits_2_naming_the_keys(tmp_path, capsys, monkeypatch):
    """A groom file's strand count is known once it is read: past the memory at hand (here made 1 MiB) its run is
    refused in one line naming the file and the keys that lower it, before the model's arrays are allocated, and
    nothing is written; within it the same scene runs."""
    from hairwarp import runner
    from hairwarp.cli import main
    from hairwarp.groom import scalp_groom
    from hairwarp.io.cem_hair import write_hair

    write_hair(tmp_path / "g.hair", scalp_groom(count=200, length=0.25, points=13, seed=3))
    scene = tmp_path / "s.toml"
    scene.write_text('[sim]\nframes = 2\n[groom]\nfile = "g.hair"\n[head]\nshape = "none"\n'
                     "[output]\npreview = false\n")
    out = tmp_path / "out"
    monkeypatch.setattr(runner, "_available_memory", lambda: 1 << 20)
    assert main(["run", str(scene), "-o", str(out / "k.usdc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "g.hair: 200 guides of" in err and "groom.max_strands" in err and "sim.segments" in err, err
    assert not out.exists() or list(out.iterdir()) == []
    monkeypatch.setattr(runner, "_available_memory", lambda: 1 << 30)
    assert main(["run", str(scene), "-o", str(out / "k.usdc")]) == 0


def test_missing_files_exit_2(tmp_path):
    for cmd in (("run", tmp_path / "nope.toml"), ("info", tmp_path / "nope.hair"), ("preview", tmp_path / "x.usdc")):
        r = _hairwarp(*cmd, cwd=tmp_path)
        assert r.returncode == 2, (cmd, r.stderr)
        assert "nope" in r.stderr or "x.usdc" in r.stderr
        assert "Traceback" not in r.stderr


def test_info_scene():
    r = _hairwarp("info", SCENES / "long_hair.toml")
    assert r.returncode == 0, r.stderr
    assert "long_hair" in r.stdout and "300 guides" in r.stdout and "90 frames" in r.stdout and "Turn(" in r.stdout
    # overrides are checked as a run would take them; on a cache they are refused
    r = _hairwarp("info", SCENES / "long_hair.toml", "-s", "sim.frames=12", "-s", "head.motion.kind='nod'")
    assert r.returncode == 0, r.stderr
    assert "12 frames" in r.stdout and "Nod(" in r.stdout and "held as drawn" not in r.stdout
    r = _hairwarp("info", SCENES / "long_hair.toml", "-s", "groom.hold_shape=true")
    assert r.returncode == 0 and "300 guides x 0.35 m, 12 segments each, held as drawn under gravity" in r.stdout
    r = _hairwarp("info", REPO / "docs" / "tunnelling.json", "-s", "sim.frames=12")
    assert r.returncode == 2 and "-s overrides apply to a scene" in r.stderr


def test_info_lists_the_colliders_and_reads_their_files(tmp_path, capsys):
    """The shoulders scene's body is listed; a usd collider whose prim is no Mesh is refused by info as a run
    refuses it (exit 2, naming the collider), not found out at run time. (``cli.main`` in this process: the
    command's own start is checked above.)"""
    from hairwarp.cli import main

    assert main(["info", str(SCENES / "long_hair_shoulders.toml")]) == 0
    out = capsys.readouterr().out
    assert "collider   shoulders: capsule radius 0.08, half height 0.16, attached to the world" in out
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "body.usda"))
    UsdGeom.Xform.Define(stage, "/Body")
    stage.Save()
    scene = tmp_path / "s.toml"
    scene.write_text("[groom]\ngenerator = 'scalp'\n[[colliders]]\nname = 'body'\nkind = 'usd'\n"
                     "file = 'body.usda'\nprim = '/Body'\n")
    assert main(["info", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "colliders[0] (body)" in err and str(scene) in err


def _write_hair(path, strands):
    """Cem Yuksel's .hair file, written here with numpy: header, uint16 segments, float32 points."""
    counts = np.array([len(s) for s in strands])
    header = struct.pack("<4sIIIIff3f88s", b"HAIR", len(strands), int(counts.sum()), 1 | 2, 0, 0.0, 0.0,
                         0.0, 0.0, 0.0, b"test groom")
    with open(path, "wb") as f:
        f.write(header)
        f.write((counts - 1).astype("<u2").tobytes())
        f.write(np.concatenate(strands).astype("<f4").tobytes())


@pytest.mark.skipif(not _has("hairwarp.groom"), reason="needs hairwarp.groom (Groom.load), not in this installation")
def test_info_groom(tmp_path):
    rng = np.random.default_rng(0)
    strands = []
    for n in (5, 9, 12):
        root = rng.uniform(-0.1, 0.1, 3) + [0.0, 0.0, 1.6]
        steps = np.tile([0.0, 0.0, -0.02], (n - 1, 1))
        strands.append(np.vstack([root, root + np.cumsum(steps, axis=0)]))
    path = tmp_path / "g.hair"
    _write_hair(path, strands)
    r = _hairwarp("info", path)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "strands  3" in out
    assert "vertices 26" in out
    lengths = [0.02 * (n - 1) for n in (5, 9, 12)]
    assert f"{min(lengths):.4g} .. {max(lengths):.4g} m" in out
    lo = np.concatenate(strands).min(axis=0)
    assert f"{lo[0]:.4g}" in out


def test_info_of_a_scene_counts_the_guides_of_its_groom_file(tmp_path, capsys):
    """A scene on a groom file: info gives the guides the file yields (not only the max_strands cap) and the up axis
    the file is read with when the scene leaves it to the format's default."""
    from hairwarp.cli import main

    _write_hair(tmp_path / "g.hair", _straight_strands((5, 6, 7, 8)))
    scene = tmp_path / "s.toml"
    scene.write_text("[groom]\nfile = 'g.hair'\nmax_strands = 10\n[head]\nshape = 'none'\n")
    assert main(["info", str(scene)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("groom"))
    assert "(up Z (the .hair default), scale 1, at most 10 strands): 4 guides" in line, line


@pytest.mark.skipif(not _has("hairwarp.groom"), reason="needs hairwarp.groom (Groom.load), not in this installation")
def test_info_bad_groom_exits_2(tmp_path):
    path = tmp_path / "g.hair"
    path.write_bytes(b"NOPE" + bytes(124))
    r = _hairwarp("info", path)
    assert r.returncode == 2 and "g.hair" in r.stderr and "Traceback" not in r.stderr


def _straight_strands(counts=(5, 6, 7)):
    return [np.column_stack([np.full(n, 0.01 * i), np.zeros(n), 1.6 - 0.02 * np.arange(n)])
            for i, n in enumerate(counts)]


def _write_usd_curves(path, strands):
    """A linear BasisCurves prim written with usd-core directly (not through hairwarp), Z up, metres."""
    from pxr import Gf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    curves = UsdGeom.BasisCurves.Define(stage, "/groom")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([len(s) for s in strands]))
    curves.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, p)) for p in np.concatenate(strands)]))
    stage.GetRootLayer().Save()


def _one_line_error(r, *words):
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in r.stderr, r.stderr


@pytest.mark.parametrize("suffix", [".hair", ".usda"])
def test_info_groom_with_a_nan_vertex_exits_2_naming_the_strand(tmp_path, suffix):
    strands = _straight_strands()
    strands[2][3, 1] = np.nan  # strand 2, vertex 3
    path = tmp_path / f"g{suffix}"
    (_write_hair if suffix == ".hair" else _write_usd_curves)(path, strands)
    _one_line_error(_hairwarp("info", path), str(path), "strand 2 vertex 3 is not finite")


def test_info_groom_with_a_one_point_strand_exits_2_naming_the_strand(tmp_path):
    path = tmp_path / "g.usda"
    _write_usd_curves(path, [*_straight_strands((5, 6)), np.array([[0.0, 0.0, 1.6]])])
    _one_line_error(_hairwarp("info", path), str(path), "strand 2 has 1 point")
    # .hair stores segments per strand: a one-point strand is 0 segments.
    path = tmp_path / "g.hair"
    _write_hair(path, [*_straight_strands((5,)), np.array([[0.0, 0.0, 1.6]]), *_straight_strands((4,))])
    _one_line_error(_hairwarp("info", path), str(path), "strand 1 has 0 segments")


def test_info_groom_reports_the_strands_dropped_as_too_short(tmp_path):
    strands = _straight_strands((5, 6, 7, 8))
    strands[1] = np.tile(strands[1][:1], (6, 1))  # six copies of its root: length 0 < min_length (1 mm)
    path = tmp_path / "g.usda"
    _write_usd_curves(path, strands)
    r = _hairwarp("info", path)
    assert r.returncode == 0, r.stderr
    assert "strands  3" in r.stdout and "vertices 20" in r.stdout  # 5 + 7 + 8 kept, as written
    assert "dropped  1 of 4 strands shorter than 0.001 m (strand 1)" in r.stdout
    assert "Warning" not in r.stderr


def _corrupt_usdc(tmp_path):
    """A crate file written by usd-core, then its second half overwritten: usd-core itself refuses it."""
    src = tmp_path / "ok.usda"
    _write_usd_curves(src, _straight_strands())
    from pxr import Tf, Usd

    path = tmp_path / "corrupt.usdc"
    Usd.Stage.Open(str(src)).Export(str(path))
    data = bytearray(path.read_bytes())
    data[len(data) // 2:] = b"\xff" * (len(data) - len(data) // 2)
    path.write_bytes(bytes(data))
    try:
        Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        return path, str(exc)
    raise AssertionError("usd-core opened the corrupt file")


def test_usd_error_text_keeps_what_went_wrong_and_drops_the_internals(tmp_path):
    from hairwarp.io.usd_common import clean_usd_text

    _, raw = _corrupt_usdc(tmp_path)
    assert "pxrInternal_" in raw and " at line " in raw  # what usd-core says, C++ places and all
    said = [line.rsplit(" : ", 1)[1].strip("'") for line in raw.strip().splitlines() if " : " in line]
    clean = clean_usd_text(raw)
    assert "\n" not in clean and "pxrInternal" not in clean and " at line " not in clean and ".cpp" not in clean
    assert clean == "; ".join(dict.fromkeys(said))  # every diagnostic usd-core gave, in its order, repeats once
    assert clean_usd_text("x: pxrInternal_v0_26_11__pxrReserved__::UsdStage::Open at line 1287") == "x: UsdStage::Open"
    ours = "a.tfxmesh: expected 'numOfBones <count>' at line 3"  # hairwarp's own line numbers stay
    assert clean_usd_text(ours) == ours


@pytest.mark.parametrize("command", ["info", "preview"])
def test_corrupt_usdc_is_one_clean_line(tmp_path, command):
    path, raw = _corrupt_usdc(tmp_path)
    r = _hairwarp(command, path)
    _one_line_error(r, str(path))
    assert "pxrInternal" not in r.stderr and " at line " not in r.stderr
    last = raw.strip().splitlines()[-1].rsplit(" : ", 1)[1].strip("'")  # usd-core's own last word on it
    assert last in r.stderr


def test_unknown_file_type_exits_2(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    r = _hairwarp("info", path)
    assert r.returncode == 2 and "notes.txt" in r.stderr and "Traceback" not in r.stderr


def test_main_in_process_returns_codes(tmp_path, capsys):
    """``main(argv)`` returns the exit code instead of exiting (for embedding and tests)."""
    from hairwarp.cli import main

    assert main(["info", str(SCENES / "tiny.toml")]) == 0
    assert "tiny" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml" in capsys.readouterr().err


class _GoneReader:
    """A standard output whose reader went away, as ``hairwarp schema | true`` leaves it."""

    def write(self, text):
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self):
        pass


@pytest.mark.parametrize("argv", [["schema"], ["info", str(SCENES / "tiny.toml")]])
def test_a_reader_gone_ends_the_command_quietly_in_process(monkeypatch, capsys, argv):
    """Output cut short by its reader: exit 141 (128 + SIGPIPE, as a command the signal ends), nothing on stderr;
    it was BrokenPipeError's traceback and exit 1."""
    from hairwarp.cli import main

    monkeypatch.setattr(sys, "stdout", _GoneReader())
    assert main(argv) == 141
    assert capsys.readouterr().err == ""


def test_a_reader_gone_ends_the_command_quietly():
    """The same through a real pipe closed before the command writes: no traceback, not even at the interpreter's
    last flush of the standard output."""
    p = subprocess.Popen([sys.executable, "-m", "hairwarp", "schema"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    p.stdout.close()
    err = p.stderr.read()
    assert p.wait(timeout=CLI_TIMEOUT_S) == 141 and err == "", err


def test_simulation_fault_exits_3(monkeypatch, tmp_path, capsys):
    """A SimulationFault from the runner becomes its message on stderr and exit code 3."""
    solver = pytest.importorskip("hairwarp.solver", reason="needs hairwarp.solver (SimulationFault)")
    runner = pytest.importorskip("hairwarp.runner", reason="needs hairwarp.runner (simulate)")
    from hairwarp.cli import main

    def fault(scene, out, **kw):
        raise solver.SimulationFault("frame 3, stage aba: joint turned 0.9 rad in one step; raise sim.substeps")

    monkeypatch.setattr(runner, "simulate", fault)
    assert main(["run", str(SCENES / "tiny.toml"), "-o", str(tmp_path / "x.usdc")]) == 3
    err = capsys.readouterr().err
    assert "frame 3, stage aba" in err and "Traceback" not in err


def test_run_passes_the_options_to_simulate(monkeypatch, tmp_path, capsys):
    runner = pytest.importorskip("hairwarp.runner", reason="needs hairwarp.runner (simulate)")
    from hairwarp.cli import main

    seen = {}

    class Result:
        cache_path = tmp_path / "out" / "tiny.usdc"
        preview_path = tmp_path / "out" / "tiny.png"
        frames = 2
        seconds = 0.5
        frame_seconds = 0.25
        seconds_per_frame = 0.125
        resumed_frames = 0
        notes = ["frame 1: a note of the run"]
        stage_seconds = None

    def fake(scene, out, **kw):
        seen.update(scene=scene, out=out, **kw)
        return Result()

    monkeypatch.setattr(runner, "simulate", fake)
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(SCENES / "tiny.toml"), "--frames", "2", "--device", "cpu", "-s", "sim.substeps=3"]) == 0
    assert "hairwarp: warning" not in capsys.readouterr().err
    # an override of a section the scene switches off (tiny has no links) runs, with a warning that names it
    assert main(["run", str(SCENES / "tiny.toml"), "-s", "links.damping=0.05", "-s", "sim.substeps=3"]) == 0
    assert capsys.readouterr().err.splitlines() == [
        "hairwarp: warning: -s links.damping: links.enabled is false in this scene, so this changes nothing; set "
        "links.enabled too"]
    assert main(["run", str(SCENES / "tiny.toml"), "--frames", "2", "--device", "cpu", "-s", "sim.substeps=3"]) == 0
    assert seen["out"] == Path("out") / "tiny.usdc"
    assert seen["frames"] == 2 and seen["device"] == "cpu" and seen["progress"] is True and seen["profile"] is False
    assert seen["scene"].sim.substeps == 3 and seen["scene"].sim.frames == 2
    out = capsys.readouterr().out
    assert "tiny.usdc" in out and "tiny.png" in out
    assert "0.50 s in all, with the set-up and the preview" in out
    assert "note     frame 1: a note of the run" in out


def test_run_prints_what_the_run_noticed(tmp_path, capsys):
    # A run's notes (contact slots grown, frames taken again, a resume that changed the simulation) end its summary;
    # the command dropped them before, so an overflow went unseen. 4 contact slots grow at once.
    from hairwarp.cli import main

    out = tmp_path / "lh.usdc"
    assert main(["run", str(SCENES / "long_hair.toml"), "--frames", "2", "-s", "interactions.capacity=4", "-s",
                 "dense.count=0", "-s", "output.preview=false", "--output", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    note = next(line for line in lines if line.startswith("note     frame 1: "))
    assert note.startswith("note     frame 1: the hair contacts' slots grew from 4 to "), note
    assert "none dropped" in note, note
    # the summary names what the time in all holds: no preview was rendered
    summary = next(line for line in lines if " simulated in " in line)
    assert summary.endswith("in all, with the set-up"), summary


@pytest.mark.skipif(not (_has("hairwarp.groom") and _has("hairwarp.io.usd_inspect")),
                    reason="needs hairwarp.groom and hairwarp.io, not in this installation")
def test_info_usd_groom_and_cache(tmp_path):
    """A static stage with curves is described as a groom too; an animated one (a cache) is not."""
    from pxr import Usd, UsdGeom, Vt

    def stage(path, animated):
        st = Usd.Stage.CreateNew(str(path))
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(st, 1.0)
        curves = UsdGeom.BasisCurves.Define(st, "/Hair")
        curves.CreateTypeAttr(UsdGeom.Tokens.linear)
        curves.CreateCurveVertexCountsAttr(Vt.IntArray([3, 2]))
        pts = [(0, 0, 1.6), (0, 0, 1.5), (0, 0, 1.4), (0.05, 0, 1.6), (0.05, 0, 1.3)]
        attr = curves.CreatePointsAttr()
        if animated:
            for frame in range(3):
                attr.Set([(x + 0.01 * frame, y, z) for x, y, z in pts], frame)
        else:
            attr.Set(pts)
        st.GetRootLayer().Save()

    stage(tmp_path / "groom.usda", animated=False)
    stage(tmp_path / "cache.usda", animated=True)
    r = _hairwarp("info", tmp_path / "groom.usda")
    assert r.returncode == 0, r.stderr
    assert "2 curves" in r.stdout and "strands  2" in r.stdout and "0.2 .. 0.3 m" in r.stdout
    r = _hairwarp("info", tmp_path / "cache.usda")
    assert r.returncode == 0, r.stderr
    assert "2 curves" in r.stdout and "strands" not in r.stdout


def test_schema_command(capsys):
    """``hairwarp schema`` prints schema_doc(); with a section, only its keys; an unknown section exits 2."""
    from hairwarp import cli
    from hairwarp.scene import schema_doc

    assert cli.main(["schema"]) == 0
    assert capsys.readouterr().out.strip() == schema_doc().strip()
    assert cli.main(["schema", "output"]) == 0
    out = capsys.readouterr().out
    assert "output.start_frame" in out and "sim.fps" not in out
    assert cli.main(["schema", "nope"]) == 2
