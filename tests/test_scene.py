"""Scene files: the shipped scenes load; every kind of error names the file and the key path; overrides."""

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hairwarp.motion import Keyframes, Nod, Turn
from hairwarp.scene import SCHEMA, ArrayOf, Field, Scene, SceneError, Section, schema_doc

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def _write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def _errors(path_or_dict, **kw):
    with pytest.raises(SceneError) as info:
        if isinstance(path_or_dict, dict):
            Scene.from_dict(path_or_dict, **kw)
        else:
            Scene.load(path_or_dict, **kw)
    return info.value


MINIMAL = """
[groom]
generator = "scalp"
"""


# ----------------------------------------------------------------------------------------------
# shipped scenes


@pytest.mark.parametrize("name", ["long_hair.toml", "tiny.toml"])
def test_shipped_scenes_load(name):
    scene = Scene.load(SCENES / name)
    assert scene.name == name.removesuffix(".toml")
    assert scene.sim.frames >= 1 and scene.sim.fps > 0
    assert scene.head.center is not None and scene.head.radii is not None
    scene.head_motion().evaluate(0.5)


def test_default_scene_is_the_bundled_long_hair():
    path = Scene.default_path()
    assert path.name == "long_hair.toml" and path.is_file()
    scene = Scene.default()
    assert scene.name == "long_hair"
    assert 250 <= scene.groom.count <= 350 and math.isclose(scene.groom.length, 0.35)
    assert scene.sim.frames / scene.sim.fps == pytest.approx(3.0)
    assert scene.head.motion.kind == "turn"
    assert isinstance(scene.head_motion(), Turn)


def test_tiny_scene_size():
    scene = Scene.load(SCENES / "tiny.toml")
    assert scene.groom.count == 8 and scene.sim.segments == 8 and scene.sim.frames == 10


def test_long_hair_documents_every_key_it_sets():
    """Each key line of the default scene carries a comment (the file is the user's manual)."""
    text = (SCENES / "long_hair.toml").read_text()
    for line in text.splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith(("#", "[")) and "=" in stripped:
            key = stripped.split("=", 1)[0].strip()
            if key not in ("name", "description", "generator"):
                assert "#" in stripped, f"long_hair.toml: key {key!r} has no comment"


# ----------------------------------------------------------------------------------------------
# defaults and typed access


def test_defaults_and_typed_access(tmp_path):
    scene = Scene.load(_write(tmp_path, MINIMAL, "my_scene.toml"))
    assert scene.name == "my_scene"
    assert scene.sim.fps == 30.0 and isinstance(scene.sim.fps, float)
    assert scene.sim.frames == 90 and isinstance(scene.sim.frames, int)
    assert scene.sim.substeps == 8 and scene.sim.integrator == "implicit_joints" and scene.sim.segments == 20
    assert scene.sim.gravity == (0.0, 0.0, -9.81)
    assert scene.groom.count == 200 and scene.groom.length == 0.3
    assert scene.strands.twist_stiffness is None
    assert scene.head.center == scene.groom.scalp_center
    assert scene.head.radii == scene.groom.scalp_radii
    # the neck: bottom of the head ellipsoid
    assert scene.head.motion.pivot == pytest.approx((0.0, 0.0, 1.6 - 0.11))
    assert scene.head.motion.keys == ()
    assert math.isinf(scene.wind.end)
    assert scene.output.guide_width == (0.002, 0.0005)
    assert scene["head.motion.kind"] == "still"
    assert scene.step_dt == pytest.approx(1.0 / 240.0)
    assert scene.wind_at(1.0) == (0.0, 0.0, 0.0)
    with pytest.raises(AttributeError, match="did you mean 'frames'"):
        _ = scene.sim.frame
    with pytest.raises(AttributeError, match="read-only"):
        scene.sim.frames = 3


def test_strand_params_match_the_model():
    from hairwarp.model import StrandParams

    scene = Scene.load(SCENES / "tiny.toml")
    p = scene.strand_params()
    assert isinstance(p, StrandParams)
    assert p.bend_stiffness == scene.strands.bend_stiffness and p.drag == scene.strands.drag
    assert set(SCHEMA["strands"].fields) == {f for f in StrandParams.__dataclass_fields__}


def test_scalp_groom_kwargs_match_the_generator_signature():
    import inspect

    from hairwarp.groom import scalp_groom

    kwargs = Scene.load(SCENES / "tiny.toml").scalp_groom_kwargs()
    assert set(kwargs) <= set(inspect.signature(scalp_groom).parameters)
    for name, param in inspect.signature(scalp_groom).parameters.items():
        field = SCHEMA["groom"].fields[name]
        assert field.default == pytest.approx(param.default), name


def test_keyframes_scene(tmp_path):
    path = _write(tmp_path, MINIMAL + """
        [head.motion]
        kind = "keyframes"
        [[head.motion.keys]]
        time = 0.0
        [[head.motion.keys]]
        time = 0.5
        rotate_deg = [0.0, 0.0, 30.0]
        [[head.motion.keys]]
        time = 1.0
        axis = [1.0, 0.0, 0.0]
        angle_deg = 10.0
        translate = [0.0, 0.01, 0.0]
    """)
    scene = Scene.load(path)
    keys = scene.head.motion.keys
    assert len(keys) == 3 and keys[1].rotate_deg == (0.0, 0.0, 30.0) and keys[2].angle_deg == 10.0
    motion = scene.head_motion()
    assert isinstance(motion, Keyframes)
    np.testing.assert_allclose(motion.evaluate(1.0).position,
                               np.asarray(scene.head.motion.pivot) + [0.0, 0.01, 0.0]
                               + _rotx(10.0) @ (-np.asarray(scene.head.motion.pivot)), atol=1e-12)


def _rotx(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def test_to_dict_round_trip(tmp_path):
    scene = Scene.load(SCENES / "long_hair.toml")
    d = scene.to_dict()
    assert d["sim"]["gravity"] == [0.0, 0.0, -9.81]
    again = Scene.from_dict(d)
    assert again.to_dict() == d


def test_groom_file_paths_are_relative_to_the_scene(tmp_path):
    (tmp_path / "grooms").mkdir()
    groom = tmp_path / "grooms" / "g.hair"
    groom.write_bytes(b"")
    sub = tmp_path / "scenes"
    sub.mkdir()
    path = _write(sub, """
        [groom]
        file = "../grooms/g.hair"
        up_axis = "Y"
        scale = 0.01
        [head]
        shape = "none"
    """)
    scene = Scene.load(path)
    assert Path(scene.groom.file) == groom.resolve()
    assert scene.groom.up_axis == "Y" and scene.groom.scale == 0.01
    assert scene.head.motion.pivot is None  # no head to put a neck under: the motion turns about the origin


# ----------------------------------------------------------------------------------------------
# errors


def test_unknown_key_suggests_the_closest(tmp_path):
    path = _write(tmp_path, MINIMAL + """
        [head.motion]
        kind = "turn"
        perod = 2.0
    """)
    err = _errors(path)
    assert str(path.resolve()) in str(err)
    assert err.errors == [("head.motion.perod", "unknown key; did you mean 'period'?")]


def test_unknown_section_suggests_the_closest(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + "[strand]\nradius = 0.001\n"))
    assert "strand: unknown key; did you mean 'strands'?" in str(err)


def test_wrong_type(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + '[sim]\nframes = "ten"\ngravity = [0, 0]\nfps = true\n'))
    text = str(err)
    assert "sim.frames: expected an integer, got a string" in text
    assert "sim.gravity: expected an array of 3 numbers" in text
    assert "sim.fps: expected a number, got a boolean" in text


def test_out_of_range(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + "[head.motion]\nkind = 'nod'\nperiod = -1.0\n"))
    assert err.errors == [("head.motion.period", "must be in (0, inf), got -1.0")]
    assert str(tmp_path) in str(err)


def test_catmull_rom_dense_curves_need_three_segments(tmp_path):
    """USD's cubic curves take 4 vertices or more: 2 segments with Catmull-Rom dense hair are refused when the scene
    loads, naming sim.segments, not when the cache is written; linear dense hair or none runs at 1 segment."""
    base = MINIMAL + "[dense]\ncount = 10\nbasis = 'catmullRom'\n"
    err = _errors(_write(tmp_path, base + "[sim]\nsegments = 2\n"))
    (path, msg), = err.errors
    assert path == "sim.segments" and "dense.basis" in msg and "got 2" in msg
    assert Scene.load(_write(tmp_path, base + "[sim]\nsegments = 3\n")).sim.segments == 3
    linear = MINIMAL + "[dense]\ncount = 10\nbasis = 'linear'\n[sim]\nsegments = 1\n"
    assert Scene.load(_write(tmp_path, linear)).sim.segments == 1


def test_a_scene_that_writes_no_hair_is_refused(tmp_path):
    """Neither guides nor dense hair in the cache: refused when the scene loads, naming output.guides (it ran and wrote
    a cache of the head alone); either one alone loads."""
    err = _errors(_write(tmp_path, MINIMAL + "[dense]\ncount = 0\n[output]\nguides = false\n"))
    (path, msg), = err.errors
    assert path == "output.guides" and "no hair" in msg
    assert Scene.load(_write(tmp_path, MINIMAL + "[dense]\ncount = 5\n[output]\nguides = false\n")).dense.count == 5
    assert Scene.load(_write(tmp_path, MINIMAL + "[dense]\ncount = 0\n")).output.guides


def test_the_default_scene_nods_about_x_when_told_to():
    """long_hair.toml leaves head.motion.axis to the kind's default, so the README's ``-s head.motion.kind=nod``
    pitches the head (about x through the neck) and its turn still yaws about z."""
    scene = Scene.load(SCENES / "long_hair.toml")
    turn = scene.head_motion().pose(0.9)[1]
    nod = scene.with_overrides(["head.motion.kind='nod'"]).head_motion().pose(0.9)[1]
    # quaternions (x, y, z, w) of a rotation about one axis: the other two components are zero
    assert abs(turn[2]) > 0.1 and abs(turn[0]) == abs(turn[1]) == 0.0
    assert abs(nod[0]) > 0.01 and abs(nod[1]) == abs(nod[2]) == 0.0


def test_bad_choice_lists_the_choices(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + "[sim]\nintegrator = 'implicit'\n"))
    (path, msg), = err.errors
    assert path == "sim.integrator"
    for choice in ("semi_implicit", "implicit_joints", "rk4"):
        assert choice in msg
    assert "did you mean 'implicit_joints'" in msg


def test_missing_groom_file_reports_the_resolved_path(tmp_path):
    path = _write(tmp_path, "[groom]\nfile = 'data/missing.tfx'\n[head]\nshape = 'none'\n")
    err = _errors(path)
    (key, msg), = err.errors
    assert key == "groom.file"
    assert str((tmp_path / "data" / "missing.tfx").resolve()) in msg
    assert str(path.resolve()) in str(err)


def test_missing_scene_file(tmp_path):
    err = _errors(tmp_path / "nope.toml")
    assert str((tmp_path / "nope.toml").resolve()) in str(err) and "not found" in str(err)


def test_toml_syntax_error(tmp_path):
    err = _errors(_write(tmp_path, "[sim\nfps = 1\n"))
    assert "not valid TOML" in str(err) and "line 1" in str(err)


@pytest.mark.parametrize(
    "text, match",
    [
        ("[groom]\ncount = 10\n", "give either generator"),
        ("[groom]\ngenerator = 'scalp'\nfile = 'x.hair'\n", "not both"),
    ],
)
def test_generator_and_file_are_exclusive(tmp_path, text, match):
    (tmp_path / "x.hair").write_bytes(b"")
    err = _errors(_write(tmp_path, text))
    assert any(path == "groom" and match in msg for path, msg in err.errors), err.errors


def test_an_override_of_the_groom_source_replaces_the_files(tmp_path):
    """-s groom.file=... on a generated scene reads that file: the generator and its keys go (the file's own error
    "give either generator or file" stays for a file that sets both); a scalp key the overrides set themselves is
    still refused; -s groom.generator=... on a file scene goes back to the scalp."""
    hair = tmp_path / "g.hair"
    hair.write_bytes(b"")
    generated = Scene.load(SCENES / "tiny.toml")
    scene = generated.with_overrides([f"groom.file='{hair}'", "head.shape='none'"])
    assert scene.groom.file == str(hair) and scene.groom.generator is None
    with pytest.raises(SceneError, match="groom.count"):
        generated.with_overrides([f"groom.file='{hair}'", "head.shape='none'", "groom.count=5"])
    back = scene.with_overrides(["groom.generator='scalp'"])
    assert back.groom.generator == "scalp" and back.groom.file is None


def test_a_motion_key_overridden_for_a_kind_that_ignores_it_is_refused():
    """-s head.motion.distance=0.05 on a turn would change nothing: refused, naming the kind that reads it; with
    kind = "translate" it is read; the file's keys for other kinds (a turn's amplitude) do not stop -s kind=still."""
    scene = Scene.load(SCENES / "long_hair.toml")
    with pytest.raises(SceneError) as info:
        scene.with_overrides(["head.motion.distance=0.05"])
    assert info.value.errors == [("head.motion.distance", "is read by kind = 'translate' only (kind is 'turn'); "
                                                          "set head.motion.kind too")]
    slide = scene.with_overrides(["head.motion.distance=0.05", "head.motion.kind='translate'"])
    assert slide.head.motion.distance == 0.05
    assert scene.with_overrides(["head.motion.kind='still'"]).head.motion.kind == "still"


def test_keys_of_a_section_the_scene_switches_off_are_named_as_unread():
    """``Scene.unread_keys``: the keys of ``links`` and ``interactions`` where the scene disables them, and of
    ``dense`` where it writes no dense hair, each with the switch to set; the switches themselves and the keys of
    sections that are on are read. ``hairwarp run`` warns of such ``-s`` overrides, ``hairwarp wedge`` refuses such a
    wedged key (``tests/test_wedge.py``)."""
    tiny = Scene.load(SCENES / "tiny.toml", ["dense.count=0"])
    assert not tiny.links.enabled and not tiny.interactions.enabled
    unread = dict(tiny.unread_keys(["links.damping", "links.enabled", "interactions.stiffness", "dense.clumping",
                                    "dense.count", "dense.density", "strands.drag", "sim.frames"]))
    assert sorted(unread) == ["dense.clumping", "interactions.stiffness", "links.damping"], unread
    assert unread["links.damping"] == "links.enabled is false in this scene, so this changes nothing; set " \
                                      "links.enabled too"
    assert "dense.count = 0" in unread["dense.clumping"] and "set dense.count too" in unread["dense.clumping"]
    assert Scene.load(SCENES / "long_hair.toml").unread_keys(["links.damping", "interactions.stiffness",
                                                              "dense.clumping"]) == []


def test_curls_the_guides_cannot_draw_are_warned_with_the_segments_they_need():
    """The scalp generator's curls (``groom.curl``) shorter than ``CURL_SEGMENTS`` guide segments along the drawn
    helix are warned of, with the segment count that draws them: 4 segments a 0.05 m curl over 0.35 m of hair is 28.
    At 12 segments the guides' chords shorten the hair from 0.35 m to about 0.22 m."""
    import warnings

    from hairwarp.runner import CURL_SEGMENTS, Simulation

    over = ["groom.count=20", "groom.curl=0.007", "dense.count=0", "links.enabled=false",
            "interactions.enabled=false", "output.preview=false"]
    need = math.ceil(CURL_SEGMENTS * 0.35 / 0.05)
    with pytest.warns(UserWarning, match=rf"groom.curl: .* spans 1.7 of the guides' segments at sim.segments = 12: .* "
                                         rf"need sim.segments >= {need}$") as caught:
        sim = Simulation(Scene.load(SCENES / "long_hair.toml", over))
    shortened = float(str(caught[0].message).split("zigzag, ")[1].split(" mm")[0])
    drawn = sim.model.seg_length.numpy().astype(float).reshape(sim.model.strand_count, -1).sum(axis=1)
    # the warning prints the length to 3 digits: within half a unit of the third
    assert shortened == pytest.approx(1e3 * np.median(drawn), abs=0.5) and shortened < 0.7 * 350.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Simulation(Scene.load(SCENES / "long_hair.toml", [*over, f"sim.segments={need}"]))
        Simulation(Scene.load(SCENES / "long_hair.toml", [*over[:1], *over[2:]]))  # straight hair


def test_a_keyframed_head_is_held_still_by_overriding_its_kind_alone():
    """-s head.motion.kind=still on a scene of [[head.motion.keys]] drops its keys (no override can remove a table; they
    were refused as keys of another kind); the head then stays at the pose the keys start from, the identity. A key
    the overrides set for a kind that does not read it is still refused, with advice that fits."""
    keyed = Scene.load(SCENES / "long_hair_shoulders.toml")
    assert keyed.head.motion.kind == "keyframes" and keyed.head.motion.keys
    still = keyed.with_overrides(["head.motion.kind='still'"])
    assert still.head.motion.kind == "still" and not still.head.motion.keys
    motion = still.head_motion()
    for t in (0.0, 0.7, 2.5):
        position, rotation = motion.pose(t)[:2]
        assert np.allclose(position, 0.0) and np.allclose(np.abs(rotation), [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(SceneError) as info:
        keyed.with_overrides(["head.motion.kind='still'", "head.motion.keys=[]"])
    assert info.value.errors == [("head.motion.keys", "is read by kind = 'keyframes' only (kind is 'still'); "
                                                      "drop this override")]


def test_keys_of_the_other_groom_source_are_rejected(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + "scale = 0.01\n"))
    assert err.errors == [("groom.scale", "applies to groom.file only, not to a generator")]


def test_all_errors_of_a_file_come_together(tmp_path):
    path = _write(tmp_path, """
        [sim]
        fram = 10
        substeps = 0
        integrator = "euler"
        [groom]
        generator = "scalp"
        length = -0.3
        [head.motion]
        kind = "keyframes"
        [[head.motion.keys]]
        time = 1.0
        [[head.motion.keys]]
        time = 0.5
        rotate_deg = [0, 0]
        [wind]
        start = 2.0
        end = 1.0
    """)
    err = _errors(path)
    paths = [p for p, _ in err.errors]
    assert paths == ["sim.fram", "sim.substeps", "sim.integrator", "groom.length", "head.motion.keys[1].rotate_deg",
                     "head.motion.keys[1].time", "wind.end"]
    assert str(err).startswith(f"{path.resolve()}: 7 errors\n")


def test_keyframes_need_keys_and_increasing_times(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + "[head.motion]\nkind = 'keyframes'\n"))
    assert err.errors[0][0] == "head.motion.keys"
    err = _errors(_write(tmp_path, MINIMAL + """
        [head.motion]
        kind = "keyframes"
        [[head.motion.keys]]
        time = 0.0
        [[head.motion.keys]]
        time = 1.0
        rotate_deg = [0.0, 0.0, 180.0]
    """))
    assert err.errors[0][0] == "head.motion.keys[1]" and "180" in err.errors[0][1]


def test_missing_required_key(tmp_path):
    err = _errors(_write(tmp_path, MINIMAL + "[head.motion]\nkind = 'keyframes'\n[[head.motion.keys]]\n"
                                             "translate = [0, 0, 0]\n"))
    assert err.errors[0][0] == "head.motion.keys[0].time" and "missing" in err.errors[0][1]


def test_from_dict_errors_name_the_source():
    err = _errors({"groom": {"generator": "scalp"}, "sim": {"fps": 0}}, source="somewhere/s.toml")
    assert "s.toml" in str(err) and err.errors == [("sim.fps", "must be in (0, inf), got 0.0")]


# ----------------------------------------------------------------------------------------------
# overrides


def test_overrides():
    scene = Scene.load(SCENES / "tiny.toml")
    fast = scene.with_overrides(["sim.frames=3", "sim.device=cuda:0", "head.motion.kind='shake'",
                                 "sim.gravity=[0, 0, -1.62]", "wind.velocity = [1.0, 0, 0]"])
    assert fast.sim.frames == 3 and fast.sim.device == "cuda:0" and fast.sim.gravity == (0.0, 0.0, -1.62)
    assert fast.head.motion.kind == "shake" and fast.wind_at(0.0) == (1.0, 0.0, 0.0)
    assert scene.sim.frames == 10  # the original is unchanged
    keyed = scene.with_overrides(["head.motion.kind='keyframes'", "head.motion.keys[0].time=0",
                                  "head.motion.keys[1].time=0.2", "head.motion.keys[1].rotate_deg=[0, 0, 20]"])
    assert len(keyed.head.motion.keys) == 2
    assert isinstance(scene.head_motion(), Nod)


def test_derived_defaults_follow_overrides():
    scene = Scene.load(SCENES / "tiny.toml").with_overrides(["groom.scalp_center=[1.0, 2.0, 1.7]"])
    assert scene.head.center == (1.0, 2.0, 1.7)
    assert scene.head.motion.pivot == pytest.approx((1.0, 2.0, 1.7 - 0.11))


def test_bad_overrides_name_the_key():
    scene = Scene.load(SCENES / "tiny.toml")
    err = _errors_of(lambda: scene.with_overrides(["sim.frames=abc", "sim.fsp=3"]))
    assert sorted(p for p, _ in err.errors) == ["sim.frames", "sim.fsp"] and "with overrides" in str(err)
    err = _errors_of(lambda: scene.with_overrides(["sim.frames"]))
    assert "key.path=value" in str(err)
    err = _errors_of(lambda: scene.with_overrides(["sim.fps.x=1"]))
    assert err.errors[0][0] == "sim.fps"
    err = _errors_of(lambda: scene.with_overrides(["head.motion.keys[5].time=1"]))
    assert "past the end" in str(err)


def _errors_of(fn):
    with pytest.raises(SceneError) as info:
        fn()
    return info.value


# ----------------------------------------------------------------------------------------------
# the schema


def test_schema_documents_every_field():
    def walk(sec):
        for name, spec in sec.fields.items():
            if isinstance(spec, Section):
                yield from walk(spec)
            elif isinstance(spec, ArrayOf):
                yield from walk(spec.section)
            else:
                yield name, spec

    sections = [sec.section if isinstance(sec, ArrayOf) else sec for sec in SCHEMA.values()]
    for name, f in (item for sec in sections for item in walk(sec)):
        assert f.doc, f"field {name} has no doc"
    doc = schema_doc()
    assert "[head.motion]" in doc and "[[head.motion.keys]]" in doc and "sim.fps = float, default 30.0" in doc


def test_schema_defaults_are_valid_toml_values():
    """Every default can be written back as TOML and read again (to_dict output is a scene file)."""
    scene = Scene.load(SCENES / "tiny.toml")
    text = _to_toml(scene.to_dict())
    assert Scene.from_dict(tomllib.loads(text)).to_dict() == scene.to_dict()


def _to_toml(d, prefix=""):
    lines, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            continue
        else:
            lines.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(lines) + "\n"
    for k, v in tables:
        name = f"{prefix}{k}"
        out += f"[{name}]\n" + _to_toml(v, name + ".")
    return out


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\") + '"'
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def test_a_new_section_is_one_entry(monkeypatch, tmp_path):
    """Adding ``[[colliders]]`` takes one schema entry; arrays of tables validate with indexed key paths."""
    collider = Section({"kind": Field("str", "sphere", "shape", choices=("sphere", "capsule")),
                        "radius": Field("float", 0.1, "radius", "m", range="(0, inf)")})
    monkeypatch.setitem(SCHEMA, "colliders", ArrayOf(collider, doc="collision shapes"))
    scene = Scene.load(_write(tmp_path, MINIMAL + "[[colliders]]\nradius = 0.2\n[[colliders]]\nkind = 'capsule'\n"))
    assert [c.radius for c in scene.colliders] == [0.2, 0.1]
    err = _errors(_write(tmp_path, MINIMAL + "[[colliders]]\nradius = 0.2\n[[colliders]]\nkind = 'box'\nradus = 1\n"))
    assert [p for p, _ in err.errors] == ["colliders[1].radus", "colliders[1].kind"]


def test_collider_keys_a_kind_does_not_read_are_refused(tmp_path):
    """A radius on a plane, a placement on a usd collider (which moves as its stage animates it, in the world): refused
    naming the kinds that read them; the keys of every kind and attach = "world" are taken."""
    err = _errors(_write(tmp_path, MINIMAL + "[[colliders]]\nname = 'floor'\nkind = 'plane'\nradius = 0.2\n"))
    assert err.errors == [("colliders[0].radius", "is read by kind = 'sphere' or 'capsule', not by 'plane'")]
    stage = tmp_path / "body.usda"
    stage.write_text("#usda 1.0\n")
    err = _errors(_write(tmp_path, MINIMAL + "[[colliders]]\nname = 'body'\nkind = 'usd'\nfile = 'body.usda'\n"
                                             "attach = 'head'\nscale = 2.0\n"))
    assert [path for path, _ in err.errors] == ["colliders[0].attach", "colliders[0].scale"]
    assert all("moves as its stage animates it" in msg for _, msg in err.errors)
    scene = Scene.load(_write(tmp_path, MINIMAL + "[[colliders]]\nname = 'egg'\nkind = 'ellipsoid'\n"
                                                  "radii = [0.2, 0.1, 0.1]\nrotate_deg = [0.0, 0.0, 90.0]\n"
                                                  "attach = 'world'\n"))
    assert scene.colliders[0].rotate_deg == (0.0, 0.0, 90.0)


def test_a_turned_ellipsoid_collider_is_turned_in_contact_and_in_the_cache():
    """An ellipsoid of radii (0.2, 0.1, 0.1) turned 90 degrees about z has its long axis along y: a point 0.15 m along
    y is inside (distance < 0), one 0.15 m along x outside by 0.05 m (float32 distances: 1e-6 m), and the mesh the
    cache shows reaches 0.2 m along y."""
    import numpy as np

    from hairwarp.runner import Simulation

    scene = Scene.load(SCENES / "tiny.toml", ["head.shape='none'"])
    raw = scene.to_dict()
    raw["colliders"] = [{"name": "egg", "kind": "ellipsoid", "radii": [0.2, 0.1, 0.1], "rotate_deg": [0.0, 0.0, 90.0],
                         "translate": [0.0, 0.0, 0.0]}]
    sim = Simulation(Scene.from_dict(raw, source=SCENES / "tiny.toml"))
    d, _, _ = sim.collider_set.signed_distance([[0.0, 0.15, 0.0], [0.15, 0.0, 0.0]])
    assert d[0, 0] < -0.01 and abs(d[1, 0] - 0.05) < 1e-6
    (_, verts, _, world), = sim.collider_meshes(0.0)
    shown = verts @ world[:3, :3].T + world[:3, 3]
    assert np.ptp(shown[:, 1]) == pytest.approx(0.4, rel=1e-3) and np.ptp(shown[:, 0]) == pytest.approx(0.2, rel=1e-3)


@pytest.mark.parametrize("kind, size, volume", [
    ("sphere", dict(radius=0.1), 4.0 / 3.0 * math.pi * 0.1 ** 3),
    ("capsule", dict(radius=0.05, half_height=0.1), math.pi * 0.05 ** 2 * (0.2 + 4.0 / 3.0 * 0.05)),
    ("ellipsoid", dict(radii=np.array([0.08, 0.1, 0.12])), 4.0 / 3.0 * math.pi * 0.08 * 0.1 * 0.12),
    ("plane", {}, 1.0 * 1.0 * 1e-3),
])
def test_analytic_colliders_display_as_closed_outward_meshes(kind, size, volume):
    """The meshes drawn for analytic colliders (tessellated without trimesh) are closed, wound outward and as large
    as the shape: trimesh finds them watertight with consistent winding and a positive volume within 1 % of the
    closed form (a grid of 32 rings by 64 sectors inscribed in a round shape misses 0.5 % of its volume; the plane's
    slab is exact), and they reach the shape's extent along every axis exactly (to float64 round-off)."""
    import trimesh

    from hairwarp.kernels.types import ColliderKind
    from hairwarp.runner import _display_mesh

    col = type("Shape", (), {"kind": ColliderKind[kind.upper()], **size})()
    verts, faces = _display_mesh(col)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(volume, rel=1e-2)
    half = {"sphere": [0.1] * 3, "capsule": [0.05, 0.05, 0.15], "ellipsoid": [0.08, 0.1, 0.12],
            "plane": [0.5, 0.5, 5e-4]}[kind]
    np.testing.assert_allclose(verts.max(axis=0), half, rtol=1e-12)
    np.testing.assert_allclose(verts.min(axis=0), -np.array(half), rtol=1e-12)


def test_collider_file_errors_name_the_collider(tmp_path):
    """A USD stage given to a mesh collider is sent to kind = "usd"; a usd collider whose prim the stage lacks fails
    when the simulation is built, naming the scene's collider as well as the file."""
    from pxr import Usd, UsdGeom

    from hairwarp.io.usd_common import UsdFileError
    from hairwarp.runner import Simulation

    stage = Usd.Stage.CreateNew(str(tmp_path / "body.usda"))
    UsdGeom.Xform.Define(stage, "/Body")
    stage.Save()
    err = _errors(_write(tmp_path, MINIMAL + "[[colliders]]\nname = 'body'\nkind = 'mesh'\nfile = 'body.usda'\n"))
    assert err.errors == [("colliders[0].file", 'a USD stage: give it as kind = "usd" (its Mesh prim, animated or '
                                                 'still)')]
    raw = Scene.load(SCENES / "tiny.toml").to_dict()
    raw["colliders"] = [{"name": "body", "kind": "usd", "file": str(tmp_path / "body.usda"), "prim": "/Body/Nope"}]
    with pytest.raises(UsdFileError, match=r"colliders\[0\] \(body\): .*body.usda"):
        Simulation(Scene.from_dict(raw, source=SCENES / "tiny.toml"))


def test_an_override_of_a_colliders_kind_drops_the_keys_the_new_kind_does_not_read(tmp_path):
    """-s colliders[0].kind="mesh" with a file on the shoulders scene turns its capsule into a mesh where the capsule
    was: its radius and half height go (they were refused as keys a mesh does not read), its placement stays."""
    mesh = tmp_path / "cap.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    shipped = Scene.load(SCENES / "long_hair_shoulders.toml")
    scene = shipped.with_overrides(["colliders[0].kind='mesh'", f"colliders[0].file='{mesh}'"])
    c, before = scene.colliders[0], shipped.colliders[0]
    assert c.kind == "mesh" and c.radius is None and c.half_height is None
    assert c.translate == before.translate and c.rotate_deg == before.rotate_deg
    with pytest.raises(SceneError, match="colliders\\[0\\].radius"):
        shipped.with_overrides(["colliders[0].kind='mesh'", f"colliders[0].file='{mesh}'", "colliders[0].radius=0.1"])


def test_dense_count_and_density_are_one_or_the_other():
    """A file's count with a density override asks for the density; both given in one place are refused naming
    dense.density (the dense hair builder took only one and said so without a key)."""
    scene = Scene.load(SCENES / "long_hair.toml")
    assert scene.dense.count == 3000
    dense = scene.with_overrides(["dense.density=20000"])
    assert dense.dense.density == 20000 and dense.dense.count == 0
    with pytest.raises(SceneError, match="dense.density"):
        scene.with_overrides(["dense.density=20000", "dense.count=100"])


def test_file_inputs_in_the_wrong_units_or_place_are_refused_or_read_in_metres(tmp_path):
    """A groom file read with ``groom.scale`` drops the strands shorter than ``min_length`` in metres, not in the
    file's units (a centimetre file kept its 0.5 mm strand, which then faulted the step); coordinates beyond
    ``MAX_COORDINATE`` (a file in the wrong units) are refused naming the file, strand and vertex, for grooms and
    collider meshes (they passed and faulted at frame 1 with advice about substeps); a folder named as a file is
    called a folder; an up_axis of "Z" asked of a .tfxmesh, which is Y up and always turned, is refused (it was
    ignored while the groom's was honoured); a scene saved with a byte-order mark loads."""
    import trimesh

    from hairwarp.colliders import Collider, ColliderError
    from hairwarp.groom import Groom
    from hairwarp.io.cem_hair import write_hair
    from hairwarp.model import MAX_COORDINATE, Model, ModelError

    strands = [np.stack([np.zeros(8), np.zeros(8), -np.linspace(0.0, length, 8)], axis=1) + (i, 0.0, 0.0)
               for i, length in enumerate((10.0, 10.0, 0.05))]  # centimetres: two 10 cm strands and a 0.5 mm one
    hair = tmp_path / "cm.hair"
    write_hair(hair, Groom.from_polylines(strands, min_length=0.0))
    raw = {"groom": {"file": str(hair), "scale": 0.01, "up_axis": "Z", "min_length": 0.001},
           "head": {"shape": "none"}}
    with pytest.warns(UserWarning, match="dropped 1 of 3 strands shorter than 0.001 m \\(strand 2\\)"):
        groom = Scene.from_dict(raw).build_groom()
    assert np.allclose(groom.lengths(), 0.1)
    unscaled = {**raw, "groom": {**raw["groom"], "scale": 1.0}}  # read as metres: 10 m strands, a warning
    with pytest.warns(UserWarning, match="strands up to 10 m long; if the file is in centimetres, set groom.scale"):
        Scene.from_dict(unscaled).build_groom()

    far = Groom.from_polylines([s * 1e4 for s in strands[:2]], min_length=0.0, source="far.hair")
    with pytest.raises(ModelError, match=f"far.hair: strand 0 vertex 7 lies at .* beyond {MAX_COORDINATE:g} m"):
        Model.build(far, segments=4)
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.apply_scale(1e5)
    with pytest.raises(ColliderError, match="vertex .* lies at .* beyond"):
        Collider.from_trimesh(box, name="box", attach="world")
    obj = tmp_path / "huge.obj"
    box.export(obj)
    with pytest.raises(ColliderError, match=f"{obj}: vertex .* lies at"):
        Collider.from_mesh_file(obj)

    (tmp_path / "folder.tfx").mkdir()
    with pytest.raises(SceneError, match="folder.tfx is a folder; name a file in it"):
        Scene.from_dict({"groom": {"file": str(tmp_path / "folder.tfx")}, "head": {"shape": "none"}})
    mesh = tmp_path / "body.tfxmesh"
    mesh.write_text("# a placeholder: not read, the scene is refused first\n")
    generated = {"groom": {"generator": "scalp"}}
    with pytest.raises(SceneError, match='head.up_axis: a .tfxmesh is Y up by definition'):
        Scene.from_dict({**generated, "head": {"shape": "mesh", "file": str(mesh), "up_axis": "Z"}})
    with pytest.raises(SceneError, match='colliders\\[0\\].up_axis: a .tfxmesh is Y up'):
        Scene.from_dict({**generated, "colliders": [{"kind": "mesh", "file": str(mesh), "up_axis": "Z"}]})

    toml = tmp_path / "bom.toml"
    toml.write_bytes(b"\xef\xbb\xbf" + b'[groom]\ngenerator = "scalp"\ncount = 4\n')
    assert Scene.load(toml).groom.count == 4
