"""Scene files: a declarative schema, validation with complete error reports, typed access.

A scene is a TOML file of sections (``[sim]``, ``[groom]``, ``[head.motion]``, ...). The schema
below, :data:`SCHEMA`, lists every section and field with its type, default, allowed range or
choices, unit and meaning; a new section is one more entry there. Loading fills in the defaults,
resolves file paths against the scene file's folder, checks every value, and reports *all* the
problems of a file together in one :class:`SceneError`::

    scene = Scene.load("scenes/long_hair.toml")
    scene.sim.fps, scene.groom.count, scene.head.motion.kind   # typed, read-only attribute access
    scene["head.motion.period"]                               # the same by key path
    fast = scene.with_overrides(["sim.frames=10", "head.motion.kind='nod'"])
    scene.to_dict()                                           # plain dict of the validated values

Typed access: a scene's sections are read-only :class:`Node` views; fields come back as Python
``float``, ``int``, ``bool``, ``str``, or tuples of floats for vectors; file fields as absolute
path strings; arrays of tables (``[[head.motion.keys]]``) as tuples of nodes; an unset optional field
is ``None`` and is left out of :meth:`Scene.to_dict`.
"""

from __future__ import annotations

import copy
import difflib
import importlib.resources
import math
import os
import re
import sys
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from hairwarp import motion as _motion

__all__ = ["REQUIRED", "SCHEMA", "ArrayOf", "Field", "Node", "Scene", "SceneError", "Section", "schema_doc"]


class SceneError(ValueError):
    """A scene file with problems; lists every problem found, each with its key path.

    Attributes:
        source: the scene file (resolved path) or a label such as ``"<dict>"``.
        errors: list of ``(key_path, message)``; key path ``""`` for the file as a whole.
    """

    def __init__(self, source: str, errors: list[tuple[str, str]]):
        self.source = str(source)
        self.errors = list(errors)
        super().__init__(self._format())

    def _format(self) -> str:
        lines = [f"{path}: {msg}" if path else msg for path, msg in self.errors]
        if len(lines) == 1:
            return f"{self.source}: {lines[0]}"
        return f"{self.source}: {len(lines)} errors\n" + "\n".join("  " + line for line in lines)

    def __reduce__(self):
        return type(self), (self.source, self.errors)


# ----------------------------------------------------------------------------------------------
# schema

_REQUIRED = object()
_TYPES = ("float", "int", "bool", "str", "path", "vec2", "vec3")
_VEC_LEN = {"vec2": 2, "vec3": 3}
_RANGE_RE = re.compile(r"^\s*([\[(])\s*(-?inf|[-+0-9.eE]+)\s*,\s*(-?inf|[-+0-9.eE]+)\s*([\])])\s*$")


@dataclass(frozen=True)
class Field:
    """One scene key.

    Attributes:
        type: ``"float"`` (an integer is accepted), ``"int"``, ``"bool"``, ``"str"``, ``"path"`` (a file
            relative to the scene file; must exist), ``"vec2"`` or ``"vec3"`` (arrays of numbers).
        default: value when the key is absent; ``None`` = unset (optional, or derived by the section's
            check); :data:`REQUIRED` = must be given.
        doc: one line saying what it does.
        unit: SI unit, ``""`` for none.
        range: interval such as ``"(0, inf)"`` or ``"[0, 1]"``, applied to every component of a vector.
        choices: allowed values of a ``"str"`` field.
        suffixes: allowed file suffixes of a ``"path"`` field (lower case, with the dot).
    """

    type: str
    default: Any = None
    doc: str = ""
    unit: str = ""
    range: str | None = None
    choices: tuple[str, ...] | None = None
    suffixes: tuple[str, ...] | None = None

    def __post_init__(self):
        if self.type not in _TYPES:
            raise TypeError(f"Field type must be one of {_TYPES}, got {self.type!r}")
        if self.range is not None and not _RANGE_RE.match(self.range):
            raise TypeError(f"Field range must look like '(0, inf)' or '[0, 1]', got {self.range!r}")

    @property
    def required(self) -> bool:
        return self.default is _REQUIRED

    def describe(self) -> str:
        """Type, default, range and unit, for documentation and ``hairwarp info``."""
        parts = [self.type]
        if self.required:
            parts.append("required")
        elif self.default is not None:
            parts.append(f"default {_fmt(self.default)}")
        if self.choices:
            parts.append("one of " + " | ".join(self.choices))
        if self.range:
            parts.append(f"in {self.range}")
        if self.unit:
            parts.append(f"[{self.unit}]")
        return ", ".join(parts)


#: Marks a :class:`Field` that must be given.
REQUIRED = _REQUIRED

#: Signature of a section check: ``check(values, given, error)``. ``values`` is the section's
#: validated dict (mutable: a check may fill derived defaults), ``given`` the keys the file set,
#: ``error(key, message)`` records a problem under the section's path (``key`` may be ``""``).
Check = Callable[[dict, set, Callable[[str, str], None]], None]


@dataclass(frozen=True)
class Section:
    """A table of fields and nested sections.

    Attributes:
        fields: name -> :class:`Field`, :class:`Section` or :class:`ArrayOf`, in documentation order.
        doc: what the section is for.
        check: optional cross-field rule, see :data:`Check`.
    """

    fields: Mapping[str, Field | Section | ArrayOf]
    doc: str = ""
    check: Check | None = None


@dataclass(frozen=True)
class ArrayOf:
    """An array of tables (``[[name]]`` in TOML), each validated by ``section``."""

    section: Section
    doc: str = ""


def _fmt(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return repr(value)


def _in_range(x: float, spec: str) -> bool:
    lo_b, lo, hi, hi_b = _RANGE_RE.match(spec).groups()
    lo, hi = float(lo), float(hi)
    ok_lo = x >= lo if lo_b == "[" else x > lo
    ok_hi = x <= hi if hi_b == "]" else x < hi
    return ok_lo and ok_hi


# ----------------------------------------------------------------------------------------------
# sections

#: Range of the strands' stiffnesses and damping. Far above any hair (EI 1e-9 to 1e-3 N m^2; a steel rod of 1 cm
#: is about 1e2) and within what float32 holds: the joints' stiffness over a segment, times the step squared and the
#: joint angles, overflows past about 1e21 (``test_strand_constants_hold_at_their_bound``).
STRAND_CONSTANT_RANGE = "[0, 1e16]"

_GROOM_SUFFIXES = (".tfx", ".hair", ".usd", ".usda", ".usdc", ".usdz")
_MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off", ".tfxmesh")
_SCALP_KEYS = ("count", "length", "points", "curl", "curl_period", "scalp_center", "scalp_radii", "cap_angle_deg",
               "front_cutoff_deg", "margin", "seed")
_FILE_KEYS = ("up_axis", "scale", "translate", "purpose")
_DEVICE_RE = re.compile(r"^(cpu|cuda(:\d+)?)$")


def _check_sim(values, given, error):
    if not _DEVICE_RE.match(values["device"]):
        error("device", f"expected 'cpu', 'cuda' or 'cuda:N', got {values['device']!r}")


def _changed(values, given, section: str, key: str) -> bool:
    """A key the file sets to something other than its default (so ``to_dict`` output reloads cleanly)."""
    return key in given and values[key] != SCHEMA[section].fields[key].default


#: Longest guide strand [m] a groom file is taken to mean without a warning about its units (hair longer than
#: 3 m is a centimetre file read as metres far more often than it is hair).
LONGEST_PLAUSIBLE_STRAND = 3.0


def _check_groom(values, given, error):
    has_gen, has_file = values["generator"] is not None, "file" in given
    if has_gen and has_file:
        error("", "give either generator or file, not both")
    elif not has_gen and not has_file:
        error("", "give either generator = \"scalp\" or file = \"path\"")
    elif has_gen:
        for key in _FILE_KEYS:
            if _changed(values, given, "groom", key):
                error(key, "applies to groom.file only, not to a generator")
    else:
        for key in _SCALP_KEYS:
            if _changed(values, given, "groom", key):
                error(key, "applies to generator = \"scalp\" only, not to groom.file")
        if values["up_axis"] is not None and Path(values["file"] or "").suffix.lower() not in (".tfx", ".hair"):
            error("up_axis", "applies to .tfx and .hair files; USD stages record their own up axis")
        if _changed(values, given, "groom", "purpose") and Path(values["file"] or "").suffix.lower() not in (
                ".usd", ".usda", ".usdc", ".usdz"):
            error("purpose", "applies to USD stages only")
    if has_gen and values["front_cutoff_deg"] > values["cap_angle_deg"]:
        error("front_cutoff_deg", f"must be at most cap_angle_deg ({values['cap_angle_deg']:g}), "
                                  f"got {values['front_cutoff_deg']:g}")
    if has_gen and 2.0 * math.pi * values["curl"] >= values["curl_period"]:
        error("curl", f"a helix needs 2 pi curl < curl_period ({values['curl_period']:g} m), got {values['curl']:g}")


def _check_surface(values, given, error):
    if values["file"] is None:
        defaults = SCHEMA["groom"].fields["surface"].fields
        for key in ("prim", "max_distance", "interpolation"):
            if key in given and values[key] != defaults[key].default:
                error(key, "applies with groom.surface.file only")
    elif values["prim"] is None:
        error("prim", "groom.surface needs the scalp's Mesh prim path")


def _check_keys(values, given, error):
    if "rotate_deg" in given and ("axis" in given or "angle_deg" in given):
        error("", "give the rotation as rotate_deg or as axis and angle_deg, not both")
    elif ("axis" in given) != ("angle_deg" in given):
        error("axis" if "angle_deg" in given else "angle_deg", "axis and angle_deg go together")
    if values["axis"] is not None and all(v == 0.0 for v in values["axis"]):
        error("axis", "must not be zero")


def _check_motion(values, given, error):
    kind, keys = values["kind"], values["keys"]
    if kind == "usd":
        for key in ("file", "prim"):
            if values[key] is None:
                error(key, "kind = \"usd\" needs file (the stage) and prim (the head's prim path)")
    else:
        for key in ("file", "prim", "joint"):
            if values[key] is not None:
                error(key, f"applies to kind = \"usd\" only (kind is \"{kind}\")")
    if kind == "keyframes" and not keys:
        error("keys", "kind = \"keyframes\" needs at least one [[head.motion.keys]] table")
    if kind != "keyframes" and keys:
        error("keys", f"keys apply to kind = \"keyframes\" only (kind is \"{kind}\")")
    if values["axis"] is not None and all(v == 0.0 for v in values["axis"]):
        error("axis", "must not be zero")
    for i in range(1, len(keys)):
        if None not in (keys[i]["time"], keys[i - 1]["time"]) and keys[i]["time"] <= keys[i - 1]["time"]:
            error(f"keys[{i}].time", f"key times must increase strictly, got {keys[i - 1]['time']:g} "
                                     f"then {keys[i]['time']:g}")


def _check_wind(values, given, error):
    if values["end"] <= values["start"]:
        error("end", f"must be after start ({values['start']:g} s), got {values['end']:g}")


def _check_head(values, given, error):
    if values["shape"] == "sphere" and values["radii"] is not None and "radii" in given:
        if len(set(values["radii"])) != 1:
            error("radii", f"a sphere needs three equal radii, got {_fmt(values['radii'])}")
    if values["shape"] == "mesh" and values["file"] is None:
        error("file", 'shape = "mesh" needs the mesh file')
    _check_tfxmesh_up_axis(values, given, error)


def _check_tfxmesh_up_axis(values, given, error):
    """A ``.tfxmesh`` is Y up by definition and always turned: ``up_axis = "Z"`` asked for was ignored while the
    groom's was honoured, and the hair sat 90 degrees off the body without a word."""
    if "up_axis" in given and values["up_axis"] == "Z" and Path(values["file"] or "").suffix.lower() == ".tfxmesh":
        error("up_axis", 'a .tfxmesh is Y up by definition (TressFX) and always turned to Z up: leave up_axis unset '
                         'or "Y"')


#: The ``[[colliders]]`` keys of one kind's shape and placement, besides :data:`_COLLIDER_COMMON`, which every kind
#: reads. A usd collider moves as its stage animates it, in the world.
_COLLIDER_COMMON = frozenset({"name", "kind", "thickness", "friction"})
_COLLIDER_KEYS = {
    "sphere": ("radius", "translate", "rotate_deg", "attach"),
    "capsule": ("radius", "half_height", "translate", "rotate_deg", "attach"),
    "plane": ("translate", "rotate_deg", "attach"),
    "ellipsoid": ("radii", "translate", "rotate_deg", "attach"),
    "mesh": ("file", "up_axis", "scale", "translate", "rotate_deg", "attach"),
    "usd": ("file", "prim"),
}


def _check_collider(values, given, error):
    kind = values["kind"]
    _check_tfxmesh_up_axis(values, given, error)
    needs = {"sphere": ("radius",), "capsule": ("radius", "half_height"), "ellipsoid": ("radii",),
             "mesh": ("file",), "usd": ("file",), "plane": ()}[kind]
    for key in needs:
        if values[key] is None:
            error(key, f'kind = "{kind}" needs {key}')
    if kind == "mesh" and values["file"] is not None and Path(values["file"]).suffix.lower() in (".usd", ".usda",
                                                                                                  ".usdc"):
        error("file", 'a USD stage: give it as kind = "usd" (its Mesh prim, animated or still)')
    for key in sorted(set(given) - set(_COLLIDER_KEYS[kind]) - _COLLIDER_COMMON):
        if key == "attach" and values[key] == "world":
            continue
        kinds = [k for k, keys in _COLLIDER_KEYS.items() if key in keys]
        why = (" (a usd collider moves as its stage animates it, in the world)" if kind == "usd" else "")
        error(key, f"is read by kind = {' or '.join(repr(k) for k in kinds)}, not by {kind!r}{why}")


def _check_scene(values, given, error):
    """Cross-section defaults: the head follows the generated scalp; the pivot is the neck."""
    groom, head = values["groom"], values["head"]
    scalp = groom["generator"] == "scalp"
    if head["center"] is None and scalp:
        head["center"] = tuple(groom["scalp_center"])
    if head["radii"] is None and scalp:
        radii = tuple(groom["scalp_radii"])
        head["radii"] = (max(radii),) * 3 if head["shape"] == "sphere" else radii
    mot = head["motion"]
    if mot["pivot"] is None and head["center"] is not None and head["radii"] is not None:
        c, r = head["center"], head["radii"]
        mot["pivot"] = (c[0], c[1], c[2] - r[2])
    dense, segments = values["dense"], values["sim"]["segments"]
    if dense["density"] is not None and dense["count"] > 0:
        error("dense.density", f"give dense.count (now {dense['count']}) or dense.density, not both: set "
                               "dense.count = 0 for a density")
    if not values["output"]["guides"] and dense["count"] == 0 and dense["density"] is None:
        error("output.guides", "is false and there is no dense hair (dense.count = 0): the cache would hold no hair; "
                               "set output.guides = true or give dense.count")
    if dense["basis"] == "catmullRom" and (dense["count"] > 0 or dense["density"] is not None) and segments < 3:
        # the cache's cubic curves take 4 vertices or more (hairwarp.io.cache); the interpolated strands have S + 1
        error("sim.segments", f"dense.basis = \"catmullRom\" needs curves of 4 vertices, 3 segments or more, got "
                              f"{segments}; raise sim.segments or set dense.basis = \"linear\"")
    if head["shape"] in ("ellipsoid", "sphere") and (head["center"] is None or head["radii"] is None) \
            and groom["file"] is not None:
        error("head", f"shape = \"{head['shape']}\" needs center and radii when the groom comes from a file")
    times = [k["time"] for k in mot["keys"]]
    if mot["kind"] == "keyframes" and times and None not in times and all(a < b for a, b in zip(times, times[1:])):
        # What only the motion can tell, e.g. consecutive keys 180 degrees apart.
        try:
            _motion.HeadMotion.from_config(mot)
        except ValueError as exc:
            where, _, msg = str(exc).partition(": ")
            error(where if msg else "head.motion.keys", msg or where)


_MOTION_KEY = Section(
    {
        "time": Field("float", REQUIRED, "time of the key", "s", range="[0, inf)"),
        "translate": Field("vec3", (0.0, 0.0, 0.0), "head translation from its rest pose, world", "m"),
        "rotate_deg": Field("vec3", None, "head rotation as extrinsic x-y-z Euler angles (Rz Ry Rx) about the pivot",
                            "deg"),
        "axis": Field("vec3", None, "rotation axis (with angle_deg), world"),
        "angle_deg": Field("float", None, "rotation angle about axis", "deg"),
    },
    doc="one key of a keyframed head motion; no rotation keeps the rest orientation",
    check=_check_keys,
)

_COLLIDER = Section(
    {
        "name": Field("str", REQUIRED, "unique name of the collider (messages, the cache's prim)"),
        "kind": Field("str", REQUIRED, "shape; usd: a Mesh prim animated in a USD stage (its transforms)",
                      choices=("sphere", "capsule", "plane", "ellipsoid", "mesh", "usd")),
        "radius": Field("float", None, "sphere, capsule: radius", "m", range="(0, inf)"),
        "half_height": Field("float", None, "capsule: half length of its axis (local z)", "m", range="[0, inf)"),
        "radii": Field("vec3", None, "ellipsoid: semi-axes along local x, y, z", "m", range="(0, inf)"),
        "file": Field("path", None, "mesh, usd: the file, relative to the scene file",
                      suffixes=_MESH_SUFFIXES + (".usd", ".usda", ".usdc")),
        "prim": Field("str", None, "usd: path of the Mesh prim (default: the first Mesh in the stage)"),
        "up_axis": Field("str", "Z", "mesh: up axis of the file (converted to Z up)", choices=("Z", "Y")),
        "scale": Field("float", 1.0, "mesh: factor to metres", range="(0, inf)"),
        "translate": Field("vec3", (0.0, 0.0, 0.0), "placement in its parent (the head or the world)", "m"),
        "rotate_deg": Field("vec3", (0.0, 0.0, 0.0), "placement: extrinsic x-y-z Euler angles; a plane's "
                                                    "normal is its local +z", "deg"),
        "attach": Field("str", "world", "head: moves with the head; world: stays put", choices=("head", "world")),
        "thickness": Field("float", 0.002, "contact layer", "m", range="[0, inf)"),
        "friction": Field("float", 0.3, "0 = frictionless sliding, 1 = full velocity match", range="[0, 1]"),
    },
    doc="one collider besides the head",
    check=_check_collider,
)

#: The scene schema: section name -> :class:`Section` (or :class:`ArrayOf` for ``[[name]]``).
SCHEMA: dict[str, Section | ArrayOf] = {
    "scene": Section(
        {
            "name": Field("str", None, "name of the scene; default: the file name without .toml"),
            "description": Field("str", "", "free text"),
        },
        doc="what the scene is",
    ),
    "sim": Section(
        {
            "fps": Field("float", 30.0, "output frames per second", "1/s", range="(0, inf)"),
            "frames": Field("int", 90, "number of output frames", range="[1, inf)"),
            "substeps": Field("int", 8, "dynamics steps per output frame", range="[1, inf)"),
            "integrator": Field("str", "implicit_joints", "time integrator of the strands",
                                choices=("semi_implicit", "implicit_joints", "rk4")),
            "segments": Field("int", 20, "simulation segments per guide strand", range="[1, 1024]"),
            "device": Field("str", "cpu", "Warp device: cpu, cuda or cuda:N"),
            "threads": Field("int", 0, "CPU threads of the launches (results are the same bits for any count); "
                                       "0: every core this process may use; ignored on CUDA", range="[0, 1024]"),
            "gravity": Field("vec3", (0.0, 0.0, -9.81), "gravitational acceleration, world", "m/s^2"),
            "max_rotation_per_step": Field("float", 1.0, "fault bound on a joint's bend in one step", "rad",
                                           range="(0, inf)"),
            "speed_margin": Field("float", 4.0, "fault bound on the guides' speed at a frame's end, as a multiple of "
                                                "the speed the head, colliders, wind and a free fall over the longest "
                                                "strand explain (inf: no bound)", range="(0, inf]"),
            "fault_retries": Field("int", 2, "times a frame that faults is taken again from its start, each time in "
                                             "twice the steps (2: in 2 and then 4 times the substeps); the run stops "
                                             "with the fault only when the last faults too (0: at once)",
                                   range="[0, 8]"),
            "whip_ratio": Field("float", 2.0, "a frame whose fastest guide vertex ends it faster than this many times "
                                              "the speed the motion explains (as sim.speed_margin measures it) is "
                                              "taken again from its start in twice the steps, up to "
                                              "sim.fault_retries times: on motion several times a scene's own, "
                                              "linked hair whips harder at long steps than at fine ones (0: never)",
                                range="[0, inf)"),
            "seed": Field("int", 0, "seed of every random choice of the run", range="[0, inf)"),
        },
        doc="time stepping and the device",
        check=_check_sim,
    ),
    "groom": Section(
        {
            "generator": Field("str", None, "generate the guides on an ellipsoidal scalp (exclusive with file)",
                               choices=("scalp",)),
            "file": Field("path", None, "groom file, relative to the scene file (exclusive with generator)",
                          suffixes=_GROOM_SUFFIXES),
            "count": Field("int", 200, "scalp: number of guide strands", range="[1, inf)"),
            "length": Field("float", 0.3, "scalp: strand length", "m", range="(0, inf)"),
            "points": Field("int", 32, "scalp: vertices per generated strand", range="[2, inf)"),
            "curl": Field("float", 0.0, "scalp: helix radius of a curl (0 = straight)", "m", range="[0, inf)"),
            "curl_period": Field("float", 0.05, "scalp: arc length of one helix turn", "m", range="(0, inf)"),
            "scalp_center": Field("vec3", (0.0, 0.0, 1.6), "scalp: centre of the scalp ellipsoid, world", "m"),
            "scalp_radii": Field("vec3", (0.085, 0.1, 0.11), "scalp: semi-axes of the scalp ellipsoid (x, y, z)", "m",
                                 range="(0, inf)"),
            "cap_angle_deg": Field("float", 110.0, "scalp: largest polar angle of a root, at the back of the head",
                                   "deg", range="(0, 180)"),
            "front_cutoff_deg": Field("float", 55.0, "scalp: largest polar angle at the forehead hairline", "deg",
                                      range="(0, 180)"),
            "margin": Field("float", 0.004, "scalp: clearance of every non-root vertex from the scalp", "m",
                            range="[0, inf)"),
            "seed": Field("int", 0, "scalp: random seed of the root jitter and lengths", range="[0, inf)"),
            "up_axis": Field("str", None, "file: up axis of a .tfx or .hair file (converted to Z up); default Y "
                                          "for .tfx, Z for .hair; USD stages record their own", choices=("Z", "Y")),
            "scale": Field("float", 1.0, "file: factor to metres", range="(0, inf)"),
            "translate": Field("vec3", (0.0, 0.0, 0.0), "file: offset after scaling and the up-axis turn", "m"),
            "min_length": Field("float", 0.001, "drop strands shorter than this", "m", range="[0, inf)"),
            "max_strands": Field("int", 0, "keep every n-th strand so at most this many remain (0 = all)",
                                 range="[0, inf)"),
            "hold_shape": Field("bool", False, "the groom as drawn is the strands' rest under gravity: each joint's "
                                               "rest bend takes the weight beyond it (inverse statics), so the hair "
                                               "starts at rest as drawn; false: the drawn shape is unloaded and sags"),
            "purpose": Field("str", "auto", "file, USD: the curves to read by UsdGeom purpose: guide, render (all "
                                            "but guides), all, or auto (the guides when the stage has both)",
                             choices=("auto", "guide", "render", "all")),
            "surface": Section(
                {
                    "file": Field("path", None, "the stage holding the scalp mesh, relative to the scene file (unset: "
                                                "the roots ride on the head)", suffixes=(".usd", ".usda", ".usdc",
                                                                                          ".usdz")),
                    "prim": Field("str", None, "the scalp's Mesh prim; its points may be time-sampled (skinned or "
                                               "blend-shaped), its transforms animated"),
                    "max_distance": Field("float", 0.01, "farthest a root may lie from the scalp at rest; each root "
                                                         "moves onto its closest point there, its strand with it",
                                          "m", range="(0, inf)"),
                    "interpolation": Field("str", "smooth", "the scalp's points between time samples, as "
                                                            "head.motion.interpolation",
                                           choices=_motion.KEY_INTERPOLATIONS),
                },
                doc="roots bound to the triangles of an animated scalp mesh (hairwarp.surface): each root rides on "
                    "its triangle's frame, so the hair follows a deforming scalp",
                check=_check_surface,
            ),
        },
        doc="the guide strands: generated on a scalp, or read from a file",
        check=_check_groom,
    ),
    "strands": Section(
        {
            "density": Field("float", 1300.0, "mass density of a guide (a wisp of hair)", "kg/m^3", range="(0, inf)"),
            "radius": Field("float", 0.002, "radius of the cylinder a guide stands for", "m", range="(0, inf)"),
            "bend_stiffness": Field("float", 2.0e-4, "bending rigidity EI of a guide", "N m^2",
                                    range=STRAND_CONSTANT_RANGE),
            "twist_stiffness": Field("float", None, "torsional rigidity GJ; default bend_stiffness / 1.3", "N m^2",
                                     range=STRAND_CONSTANT_RANGE),
            "damping": Field("float", 2.0e-7, "internal bending and twisting damping", "N m^2 s",
                             range=STRAND_CONSTANT_RANGE),
            "root_stiffness_scale": Field("float", 1.0, "factor on the root joint's stiffness and damping",
                                          range="[0, inf)"),
            "drag": Field("float", 0.01, "linear air drag per unit length (0 = off; wind acts through it)",
                          "N s/m^2", range="[0, inf)"),
        },
        doc="physical parameters of the guide strands (hairwarp.StrandParams)",
    ),
    "head": Section(
        {
            "shape": Field("str", "ellipsoid", "collision shape of the head: an analytic ellipsoid or sphere, a "
                                              "mesh file, or none", choices=("ellipsoid", "sphere", "mesh", "none")),
            "center": Field("vec3", None, "centre of the head shape, world; default: the scalp centre", "m"),
            "radii": Field("vec3", None, "semi-axes of the head shape; default: the scalp radii", "m",
                           range="(0, inf)"),
            "file": Field("path", None, "shape = mesh: the head or body mesh, relative to the scene file",
                          suffixes=_MESH_SUFFIXES),
            "up_axis": Field("str", "Z", "shape = mesh: up axis of the mesh file (converted to Z up)",
                             choices=("Z", "Y")),
            "scale": Field("float", 1.0, "shape = mesh: factor to metres", range="(0, inf)"),
            "translate": Field("vec3", (0.0, 0.0, 0.0), "shape = mesh: offset after scaling and the up-axis turn",
                               "m"),
            "thickness": Field("float", 0.002, "contact layer: closer vertices take the head's velocity, "
                                               "pushed-out vertices land this far above it", "m", range="[0, inf)"),
            "friction": Field("float", 0.3, "0 = hair slides freely, 1 = the head carries it along (full match)",
                              range="[0, 1]"),
            "teleport_distance": Field("float", 0.2, "a head that carries the middle of its hair farther than this "
                                                     "within one frame (a cut, a respawn) carries the hair rigidly "
                                                     "and resets its velocities; inf = never", "m", range="(0, inf]"),
            "teleport_angle_deg": Field("float", 60.0, "the same for a head that turns farther than this within one "
                                                       "frame", "deg", range="(0, 180]"),
            "motion": Section(
                {
                    "kind": Field("str", "still", "how the head moves", choices=_motion.MOTION_KINDS),
                    "amplitude_deg": Field("float", _motion.DEFAULT_AMPLITUDE_DEG,
                                           "turn, nod, shake: largest angle", "deg", range="[-180, 180]"),
                    "period": Field("float", _motion.DEFAULT_PERIOD, "duration of one cycle", "s", range="(0, inf)"),
                    "start": Field("float", _motion.DEFAULT_START, "time the motion begins", "s", range="[0, inf)"),
                    "ramp": Field("float", _motion.DEFAULT_RAMP, "fade-in time of the amplitude (0 = abrupt)", "s",
                                  range="[0, inf)"),
                    "axis": Field("vec3", None, "rotation axis or, for translate, direction; default: z for turn "
                                                "and shake, x for nod and translate"),
                    "distance": Field("float", _motion.DEFAULT_DISTANCE, "translate: amplitude", "m"),
                    "pivot": Field("vec3", None, "world point the head turns about; default: the neck, "
                                                 "center - (0, 0, radii.z)", "m"),
                    "keys": ArrayOf(_MOTION_KEY, doc="keyframes: the keys, in time order"),
                    "file": Field("path", None, "usd: the stage holding the head's animation (played from its "
                                                "startTimeCode), relative to the scene "
                                                "file", suffixes=(".usd", ".usda", ".usdc", ".usdz")),
                    "prim": Field("str", None, "usd: the head's prim path in that stage, e.g. /Character/Head, or "
                                               "a Skeleton's (with joint); the head moves as it does from its first "
                                               "time sample on"),
                    "joint": Field("str", None, "usd, when prim is a UsdSkel Skeleton: the joint that carries the "
                                                "head, its path as in the skeleton's joints (Hips/Spine/Neck/Head) "
                                                "or its last name when unique; the head moves as the joint does "
                                                "(its bound SkelAnimation, times the skeleton prim's transform)"),
                    "interpolation": Field("str", "smooth",
                                           "keyframes, usd: smooth (Catmull-Rom, C1; overshoots before a jump), "
                                           "monotone (no overshoot, C1) or linear (constant speed between keys)",
                                           choices=_motion.KEY_INTERPOLATIONS),
                },
                doc="rigid motion of the head (hairwarp.motion)",
                check=_check_motion,
            ),
        },
        doc="the head: the strands' base and a collider",
        check=_check_head,
    ),
    "wind": Section(
        {
            "velocity": Field("vec3", (0.0, 0.0, 0.0), "wind velocity, world", "m/s"),
            "start": Field("float", 0.0, "time the wind starts", "s", range="[0, inf)"),
            "end": Field("float", math.inf, "time the wind stops", "s"),
        },
        doc="uniform wind, on between start and end (a gust); acts through strands.drag",
        check=_check_wind,
    ),
    "colliders": ArrayOf(_COLLIDER, doc="colliders besides the head: shoulders, a body, the floor"),
    "links": Section(
        {
            "enabled": Field("bool", False, "static links: breakable zero-rest-length springs between neighbours"),
            "neighbours": Field("int", 3, "links per segment to its nearest segments of other strands",
                                range="[1, 32]"),
            "radius": Field("float", 0.012, "largest distance of a linked segment at rest", "m", range="(0, inf)"),
            "stiffness": Field("float", 2.0, "spring stiffness k_s of a link between segments 1 cm long; each link "
                               "takes it times the mean length of its two segments over 1 cm, so the hair is tied "
                               "alike at any sim.segments", "N/m", range="[0, inf)"),
            "damping": Field("float", 0.004, "spring damping k_d of a link between segments 1 cm long, scaled as the "
                             "stiffness; with the links in the free step, capped on a segment whose links' dampers "
                             "together would take more than its velocity in a step (docs/interactions.md)", "N s/m",
                             range="[0, inf)"),
            "break_length": Field("float", 0.03, "a link stretched past this breaks for good", "m",
                                  range="(0, inf)"),
            "break_step": Field("float", 1.0 / 120.0, "longest step a link may break at: a frame of longer steps in "
                                "which a link breaks is taken again in steps this long, and its breaks are that "
                                "frame's (0: links break at any step)", "s", range="[0, inf)"),
            "response": Field("str", "auto", "link forces solved after the free step, inside the strands' dynamics, on "
                              "the relative motion of their ends (step), or each link alone against its free "
                              "segments' masses (link); auto: step at steps of 1/220 s or longer and for links too "
                              "stiff for the free step (step times sqrt(k/m) above 0.7), else link",
                              choices=("auto", "step", "link")),
            "sweeps": Field("int", 1, "with the step response: Gauss-Seidel sweeps over the strands' links and "
                            "hair contacts after the free step, per step of up to 1/240 s that starts from the "
                            "links' last force (the warm start, at steps under 1/45 s), a step k times as long k^2 "
                            "times as many (16 at 1/60 s); a step that starts cold, or at longer steps from the share "
                            "of that force its ends' parting leaves, twice as many, k^1.5 times those "
                            "(25 at one step a frame); and at least 4, 12 or 16 times this many for links (or swept "
                            "contacts) stiffer than the step holds on one (the step times sqrt(k/m) past 8, 10, 85); "
                            "more hold the hair nearer its backward-Euler step, each costs about one more response "
                            "solve",
                            range="[1, 64]"),
        },
        doc="static links (hairstyle cohesion and recovery; hairwarp.interactions.StaticLinks)",
    ),
    "interactions": Section(
        {
            "enabled": Field("bool", False, "dynamic hair-hair contacts: repulsion and friction"),
            "threshold": Field("float", 0.002, "pairs closer than this interact", "m", range="(0, inf)"),
            "stiffness": Field("float", 8.0, "repulsion stiffness k0; vertex-face contacts scale it by the strips' "
                               "local density and by the vertex's segment length over 1 cm (one contact a vertex: "
                               "alike at any sim.segments)", "N/m", range="[0, inf)"),
            "damping": Field("float", 0.004, "normal damping; vertex-face contacts scale it by the vertex's segment "
                             "length over 1 cm (not by the density); in the free step (response mass) a pair's at most "
                             "stops its approach in one step", "N s/m", range="[0, inf)"),
            "friction": Field("float", 0.3, "Coulomb friction coefficient", range="[0, inf)"),
            "vertex_face": Field("bool", True, "vertex against the triangle strips between guides with adjacent roots"),
            "segment_segment": Field("bool", True, "segment against segment of different strands"),
            "detect": Field("str", "frame", "find contact pairs every step, or once per frame with a margin",
                            choices=("step", "frame")),
            "margin": Field("float", 0.001, "detect = frame: pairs within threshold + margin are kept for the frame; "
                            "a pair that closes in from farther pushes from the next frame on (the share of pairs "
                            "missed: hairwarp bench interactions)", "m", range="[0, inf)"),
            "capacity": Field("int", 0, "contact slots to start with (0 = 16 per segment); a run grows them where "
                              "it finds more pairs, and notes it", range="[0, inf)"),
            "response": Field("str", "auto", "contact forces solved after the free step, inside the strands' "
                              "dynamics, on each pair's relative motion (step), or explicit with the semi-implicit "
                              "mass on every motion (mass); auto: step at steps of 1/220 s or longer and for "
                              "contacts too stiff for the free step (the step times sqrt(k/m) past 6), else mass",
                              choices=("auto", "step", "mass")),
        },
        doc="dynamic interactions (hairwarp.interactions.HairContacts on TriangleStrips)",
    ),
    "dense": Section(
        {
            "count": Field("int", 0, "dense strands interpolated from the guides (0 = none)", range="[0, inf)"),
            "density": Field("float", None, "dense strands per m^2 of scalp, instead of count", "1/m^2",
                             range="(0, inf)"),
            "samples_per_segment": Field("int", 4, "Hermite samples per guide segment (1 = no smoothing); the "
                                                   "linear basis and previews: Catmull-Rom curves take the "
                                                   "interpolated vertices",
                                         range="[1, 64]"),
            "basis": Field("str", "linear", "linear curves over the Hermite samples, or Catmull-Rom curves "
                                            "over the interpolated vertices (smaller files)",
                           choices=("linear", "catmullRom")),
            "length_variation": Field("float", 0.1, "strand lengths vary in [1 - this, 1] of the guides'",
                                      range="[0, 1)"),
            "tip_spread": Field("float", 0.005, "random offset of a strand's tip from its interpolated path", "m",
                                range="[0, inf)"),
            "clumping": Field("float", 0.2, "pull toward the nearest guide, growing toward the tip", range="[0, 1]"),
            "width": Field("vec2", (1.0e-4, 2.0e-5), "dense curve width at the root and at the tip", "m",
                           range="[0, inf)"),
            "velocities": Field("bool", True, "write velocities for motion blur"),
            "push_out": Field("bool", True, "push interpolated vertices out of the body colliders (interpolated "
                                            "hair can cut into heads)"),
            "seed": Field("int", 0, "seed of the root sampling and the per-strand variation", range="[0, inf)"),
        },
        doc="dense hair interpolated from the guides and smoothed with Hermite splines (hairwarp.DenseHair)",
    ),
    "output": Section(
        {
            "guides": Field("bool", True, "write the guide strands to the cache (false needs dense hair)"),
            "guide_width": Field("vec2", (0.002, 0.0005), "guide curve width at the root and at the tip", "m",
                                 range="[0, inf)"),
            "preview": Field("bool", True, "render a preview image next to the cache"),
            "preview_frames": Field("int", 4, "frames shown in the preview (at most the sim.frames + 1 written)",
                                    range="[1, inf)"),
            "writer": Field("str", "inline", "who writes the cache: the simulating thread (inline), or a second "
                                             "process while the simulation goes on (background; needs a free core)",
                            choices=("inline", "background")),
            "layout": Field("str", "clips", "the cache: a root layer over clip layers, one a frame (small frames "
                                            "gathered into one clip when the run ends) (clips), or one file "
                                            "flattened at the end (single)", choices=("clips", "single")),
            "up_axis": Field("str", "Z", "up axis of the cache stage (points are rotated into it; Maya and Houdini "
                                         "work Y up)", choices=("Z", "Y")),
            "meters_per_unit": Field("float", 1.0, "unit of the cache stage (0.01 = centimetres, as Maya and "
                                                   "Unreal)", "m", range="(0, inf)"),
            "start_frame": Field("int", 0, "time code of the first frame in the cache (shots often start at 1001)",
                                 range="[0, inf)"),
            "collider_purpose": Field("str", "proxy", "UsdGeom purpose of the collider meshes: proxy (shown in "
                                                      "viewports, not rendered) or render",
                                      choices=("proxy", "render")),
        },
        doc="what a run writes",
    ),
}

_ROOT = Section(SCHEMA, doc="a hairwarp scene", check=_check_scene)


def _finite_allowed(value: float, f: Field) -> bool:
    """NaN is never a value; an infinity only where it is the field's default (e.g. ``wind.end``: never stops) or
    its range includes it (``(0, inf]``: ``head.teleport_distance = inf`` turns teleports off)."""
    if math.isfinite(value):
        return True
    if math.isnan(value):
        return False
    return (isinstance(f.default, float) and value == f.default) or (
        value > 0 and f.range is not None and f.range.replace(" ", "").endswith("inf]"))


# ----------------------------------------------------------------------------------------------
# validation


class _Validator:
    def __init__(self, base_dir: Path):
        self.base_dir = base_dir
        self.errors: list[tuple[str, str]] = []

    def error(self, path: str, msg: str):
        self.errors.append((path, msg))

    def section(self, sec: Section, raw, path: str) -> dict:
        if not isinstance(raw, Mapping):
            self.error(path, f"expected a table, got {_type_name(raw)}")
            raw = {}
        known = list(sec.fields)
        for key in raw:
            if key not in sec.fields:
                self.error(_join(path, key), _unknown_key_msg(key, known))
        out = {}
        for name, spec in sec.fields.items():
            sub = _join(path, name)
            if isinstance(spec, Section):
                out[name] = self.section(spec, raw.get(name, {}), sub)
            elif isinstance(spec, ArrayOf):
                items = raw.get(name, [])
                if not isinstance(items, list):
                    self.error(sub, f"expected an array of tables ([[{sub}]]), got {_type_name(items)}")
                    items = []
                out[name] = [self.section(spec.section, item, f"{sub}[{i}]") for i, item in enumerate(items)]
            elif name in raw:
                out[name] = self.field(spec, raw[name], sub)
            else:
                if spec.required:
                    self.error(sub, f"missing required key ({spec.doc})")
                out[name] = None if spec.required else copy.deepcopy(spec.default)
        if sec.check is not None:
            given = {k for k in raw if k in sec.fields}
            try:
                sec.check(out, given, lambda key, msg: self.error(_join(path, key), msg))
            except (TypeError, KeyError):
                # A check tripping over a value already reported as invalid adds nothing new.
                if not self.errors:
                    raise
        return out

    def field(self, f: Field, value, path: str):
        if f.type in ("float", "int"):
            ok = _is_number(value) if f.type == "float" else isinstance(value, int) and not isinstance(value, bool)
            if not ok:
                want = "a number" if f.type == "float" else "an integer"
                self.error(path, f"expected {want}, got {_type_name(value)} {_show(value)}")
                return f.default if f.default is not REQUIRED else None
            value = float(value) if f.type == "float" else int(value)
            if f.type == "float" and not _finite_allowed(value, f):
                self.error(path, f"must be a finite number, got {_show(value)}")
            elif f.range and not _in_range(value, f.range):
                self.error(path, f"must be in {f.range}, got {_show(value)}")
            return value
        if f.type in _VEC_LEN:
            n = _VEC_LEN[f.type]
            if not (isinstance(value, list) and len(value) == n and all(_is_number(v) for v in value)):
                self.error(path, f"expected an array of {n} numbers, got {_type_name(value)} {_show(value)}")
                return f.default
            value = tuple(float(v) for v in value)
            if not all(_finite_allowed(v, f) for v in value):
                self.error(path, f"must contain finite numbers only, got {_show(list(value))}")
            elif f.range and not all(_in_range(v, f.range) for v in value):
                self.error(path, f"every component must be in {f.range}, got {_show(list(value))}")
            return value
        if f.type == "bool":
            if not isinstance(value, bool):
                self.error(path, f"expected true or false, got {_type_name(value)} {_show(value)}")
                return f.default
            return value
        if not isinstance(value, str):
            self.error(path, f"expected a string, got {_type_name(value)} {_show(value)}")
            return f.default
        if f.choices is not None and value not in f.choices:
            low = value.lower()
            close = [c for c in f.choices if c.lower().startswith(low)] if low else []
            close = close if len(close) == 1 else difflib.get_close_matches(value, f.choices, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            self.error(path, f"unknown choice {value!r}; choose one of {', '.join(f.choices)}{hint}")
        if f.type == "path":
            p = Path(value).expanduser()
            resolved = (p if p.is_absolute() else self.base_dir / p).resolve()
            if f.suffixes and resolved.suffix.lower() not in f.suffixes:
                self.error(path, f"unsupported file type {resolved.suffix or '(none)'!r} of {resolved}; "
                                 f"expected one of {', '.join(f.suffixes)}")
            elif resolved.is_dir():
                self.error(path, f"{resolved} is a folder; name a file in it")
            elif not resolved.is_file():
                self.error(path, f"file not found: {resolved} (relative paths start at {self.base_dir})")
            return str(resolved)
        return value


def _join(path: str, key: str) -> str:
    if not key:
        return path
    return f"{path}.{key}" if path else key


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _type_name(v) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "an array"
    if isinstance(v, Mapping):
        return "a table"
    return type(v).__name__


def _show(v) -> str:
    text = _fmt(v) if isinstance(v, (bool, str, int, float, list, tuple)) else repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _unknown_key_msg(key: str, known: list[str]) -> str:
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    if close:
        return f"unknown key; did you mean {close[0]!r}?"
    return "unknown key; known keys: " + ", ".join(known)


def _strip_none(value):
    if isinstance(value, dict):
        return {k: _strip_none(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        return [_strip_none(v) for v in value]
    return value


# ----------------------------------------------------------------------------------------------
# typed access


class Node:
    """A read-only view of a validated table: ``node.key`` or ``node["key"]``; nested tables are nodes.

    Field names take precedence over the methods (``motion.keys`` is the array of key tables).
    Iterating a node gives its key names; ``key in node`` tests one; :meth:`to_dict` copies it.
    """

    __slots__ = ("_data", "_path")

    def __init__(self, data: dict, path: str = ""):
        object.__setattr__(self, "_data", data)
        object.__setattr__(self, "_path", path)

    def __getattribute__(self, name: str):
        if not name.startswith("_"):
            data = object.__getattribute__(self, "_data")
            if name in data:
                return _wrap(data[name], _join(object.__getattribute__(self, "_path"), name))
        return object.__getattribute__(self, name)

    def __getattr__(self, name: str):
        data = object.__getattribute__(self, "_data")
        close = difflib.get_close_matches(name, list(data), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise AttributeError(f"scene has no key {_join(self._path, name)!r}{hint}")

    def __getitem__(self, key: str):
        if key not in self._data:
            raise KeyError(key)
        return _wrap(self._data[key], _join(self._path, key))

    def __contains__(self, key) -> bool:
        return key in self._data

    def __iter__(self):
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __setattr__(self, name, value):
        raise AttributeError("scene values are read-only; use Scene.with_overrides")

    def to_dict(self) -> dict:
        """A deep copy as plain dicts and lists, unset values left out."""
        return _strip_none(copy.deepcopy(self._data))

    def __repr__(self) -> str:
        return f"Node({self._path or '<root>'}: {', '.join(self._data)})"


def _wrap(value, path: str):
    if isinstance(value, dict):
        return Node(value, path)
    if isinstance(value, list):
        return tuple(_wrap(v, f"{path}[{i}]") for i, v in enumerate(value))
    return value


# ----------------------------------------------------------------------------------------------
# the scene


class Scene:
    """A validated scene. Sections are attributes (:class:`Node`), e.g. ``scene.sim.fps``.

    Attributes:
        source: the scene file (absolute path) or None for a scene built from a dict.
        base_dir: folder that relative file paths were resolved against.
        raw: the table as given (before defaults), used to re-validate with overrides.
        name: ``scene.name``, or the file's stem, or ``"scene"``.
    """

    def __init__(self, data: dict, raw: dict, source: Path | None, base_dir: Path, label: str):
        self._data = data
        self.raw = raw
        self.source = source
        self.base_dir = base_dir
        self._label = label

    # construction ---------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str | Path, overrides: Iterable[str] = ()) -> Scene:
        """Read and validate a TOML scene file.

        Args:
            path: the scene file.
            overrides: ``"key.path=value"`` strings applied before validation (see :meth:`with_overrides`).

        Raises:
            SceneError: the file is missing, is not valid TOML, or has invalid values (all listed).
        """
        resolved = Path(path).expanduser().resolve()
        try:
            text = resolved.read_text(encoding="utf-8-sig")  # a byte-order mark, as Windows editors write, is no TOML
        except FileNotFoundError:
            raise SceneError(str(resolved), [("", "scene file not found")]) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise SceneError(str(resolved), [("", f"cannot read the scene file: {exc}")]) from None
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(str(resolved), [("", f"not valid TOML: {exc}")]) from None
        return cls._build(raw, resolved, resolved.parent, str(resolved), overrides)

    @classmethod
    def from_dict(cls, d: Mapping, source: str | Path | None = None, *, base_dir: str | Path | None = None,
                  overrides: Iterable[str] = ()) -> Scene:
        """Validate a scene given as a dict (the parsed TOML).

        Args:
            d: the tables.
            source: the file the dict came from, for messages and relative paths; None for none.
            base_dir: folder for relative file paths; default the source's folder, else the current one.
            overrides: ``"key.path=value"`` strings applied before validation.
        """
        src = Path(source).expanduser().resolve() if source is not None else None
        if base_dir is None:
            base_dir = src.parent if src is not None else Path.cwd()
        label = str(src) if src is not None else "<dict>"
        return cls._build(copy.deepcopy(dict(d)), src, Path(base_dir).resolve(), label, overrides)

    @classmethod
    def coerce(cls, scene) -> Scene:
        """``scene`` as a Scene: a Scene as it is, a path (str or ``os.PathLike``) loaded, a dict validated."""
        if isinstance(scene, Scene):
            return scene
        if isinstance(scene, str | os.PathLike):
            return cls.load(scene)
        if isinstance(scene, Mapping):
            return cls.from_dict(scene)
        raise TypeError(f"scene must be a hairwarp Scene, a scene file's path or its tables as a dict, got "
                        f"{type(scene).__name__}")

    @classmethod
    def default_path(cls) -> Path:
        """The bundled default scene, ``long_hair.toml``."""
        return Path(str(importlib.resources.files("hairwarp.scenes") / "long_hair.toml"))

    @classmethod
    def default(cls) -> Scene:
        """Load the bundled default scene."""
        return cls.load(cls.default_path())

    @classmethod
    def _build(cls, raw: dict, source: Path | None, base_dir: Path, label: str, overrides: Iterable[str]) -> Scene:
        if isinstance(overrides, str | bytes):
            raise TypeError(f"overrides must be a list of \"key.path=value\" strings, got one string "
                            f"{overrides!r} (write [{overrides!r}])")
        overrides = list(overrides)
        if overrides:
            raw = copy.deepcopy(raw)
            problems = []
            keys = _override_keys(overrides)
            _switch_groom_source(raw, keys)
            for text in overrides:
                try:
                    _apply_override(raw, text)
                except ValueError as exc:
                    problems.append(exc.args[0])
            _switch_collider_kinds(raw, keys)
            _switch_motion_kind(raw, keys)
            _switch_dense_amount(raw, keys)
            if problems:
                raise SceneError(label, problems)
            label = f"{label} (with overrides)"
        v = _Validator(base_dir)
        data = v.section(_ROOT, raw, "")
        if not v.errors:
            v.errors.extend(_unread_motion_overrides(data["head"]["motion"]["kind"], _override_keys(overrides)))
        if v.errors:
            raise SceneError(label, v.errors)
        if data["scene"]["name"] is None:
            data["scene"]["name"] = source.stem if source is not None else "scene"
        return cls(data, raw, source, base_dir, label)

    def unread_keys(self, keys: Iterable[str]) -> list[tuple[str, str]]:
        """The keys of ``keys`` (``section.key`` paths, as overrides give them) that this scene does not read because
        their section is switched off (``links`` and ``interactions`` with ``enabled = false``, ``dense`` with no
        count or density), each with why: an override of such a key changes nothing."""
        off = {}
        if not self.links.enabled:
            off["links"] = ("links.enabled", "links.enabled is false in this scene")
        if not self.interactions.enabled:
            off["interactions"] = ("interactions.enabled", "interactions.enabled is false in this scene")
        if not self.dense.count and self.dense.density is None:
            off["dense"] = ("dense.count", "the scene writes no dense hair (dense.count = 0)")
        unread = []
        for key in keys:
            section = key.split(".", 1)[0]
            if section in off and key not in (off[section][0], "dense.density"):
                unread.append((key, f"{off[section][1]}, so this changes nothing; set {off[section][0]} too"))
        return unread

    def with_overrides(self, overrides: Iterable[str]) -> Scene:
        """A new scene with ``"key.path=value"`` changes, re-validated.

        The value is read as a TOML value (``sim.frames=10``, ``sim.gravity=[0, 0, -1]``,
        ``head.motion.kind="nod"``); a value that is not valid TOML is taken as a string
        (``sim.device=cuda``). ``head.motion.keys[1].time=0.5`` indexes an array of tables
        (the index may be one past the end to add a table).

        Raises:
            SceneError: a malformed override or an invalid result; the messages name the keys.
        """
        return self._build(self.raw, self.source, self.base_dir, str(self.source or "<dict>"), overrides)

    # access -----------------------------------------------------------------------------------

    def __getattr__(self, name: str):
        if name.startswith("_") or name not in self._data:
            if name.startswith("_"):
                raise AttributeError(name)
            close = difflib.get_close_matches(name, list(self._data), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise AttributeError(f"scene has no section {name!r}{hint}")
        return _wrap(self._data[name], name)

    def __getitem__(self, path: str):
        """Value at a dotted key path, e.g. ``scene["head.motion.period"]`` or ``"head.motion.keys[0].time"``."""
        value: Any = self._data
        for part, index in _split_path(path):
            if not isinstance(value, dict) or part not in value:
                raise KeyError(path)
            value = value[part]
            if index is not None:
                if not isinstance(value, list) or index >= len(value):
                    raise KeyError(path)
                value = value[index]
        return _wrap(value, path)

    @property
    def name(self) -> str:
        return self._data["scene"]["name"]

    @property
    def frame_dt(self) -> float:
        """Time between output frames [s]."""
        return 1.0 / self._data["sim"]["fps"]

    @property
    def step_dt(self) -> float:
        """Dynamics step [s]: ``1 / (fps * substeps)``."""
        return 1.0 / (self._data["sim"]["fps"] * self._data["sim"]["substeps"])

    def to_dict(self) -> dict:
        """Every validated value (defaults filled, paths absolute) as plain dicts; unset values left out.

        ``Scene.from_dict(scene.to_dict())`` gives the same scene.
        """
        return _strip_none(copy.deepcopy(self._data))

    def head_motion(self) -> _motion.HeadMotion:
        """The head motion of ``[head.motion]``; the head frame is the world frame at rest."""
        return _motion.HeadMotion.from_config(self._data["head"]["motion"])

    def wind_at(self, t: float) -> tuple[float, float, float]:
        """Wind velocity at time ``t`` [m/s]: ``wind.velocity`` for ``start <= t < end``, else zero."""
        w = self._data["wind"]
        return tuple(w["velocity"]) if w["start"] <= t < w["end"] else (0.0, 0.0, 0.0)

    def strand_params(self):
        """``hairwarp.StrandParams`` of the ``[strands]`` section."""
        from hairwarp.model import StrandParams

        return StrandParams(**self._data["strands"])

    def scalp_groom_kwargs(self) -> dict:
        """Keyword arguments of ``hairwarp.groom.scalp_groom`` for ``generator = "scalp"``."""
        g = self._data["groom"]
        if g["generator"] != "scalp":
            raise ValueError(f"{self._label}: groom.generator is not \"scalp\"")
        return {k: g[k] for k in _SCALP_KEYS}

    def build_groom(self):
        """The guide strands of ``[groom]`` as a ``hairwarp.Groom`` (metres, Z up).

        A generator is called with the scalp keys; a file is read with ``min_length`` and ``up_axis``,
        scaled by ``scale``, then moved by ``translate``. Last, ``max_strands > 0`` keeps every n-th
        strand, ``n = ceil(G / max_strands)``.

        Raises:
            GroomError: the generator or the reader rejects its input (the message names the file).
        """
        from hairwarp import groom as _groom

        g = self._data["groom"]
        if g["generator"] == "scalp":
            groom = _groom.scalp_groom(**self.scalp_groom_kwargs())
        else:
            up = g["up_axis"].lower() if g["up_axis"] else None
            usd = Path(g["file"]).suffix.lower() in (".usd", ".usda", ".usdc", ".usdz")
            extra = {"purpose": g["purpose"]} if usd else {}
            scaled = g["scale"] != 1.0
            # min_length is in metres: a scaled file's strands are measured once scaled (a centimetre file read with
            # scale 0.01 kept its 0.5 mm strands, whose segments then faulted the step)
            groom = _groom.Groom.load(g["file"], min_length=0.0 if scaled else g["min_length"], up_axis=up, **extra)
            if scaled or any(g["translate"]):
                m = np.eye(4)
                m[:3, :3] *= g["scale"]
                m[:3, 3] = g["translate"]
                groom = groom.transformed(m)
            if scaled:
                groom = groom.without_short(g["min_length"])
            longest = float(groom.lengths().max())
            if longest > LONGEST_PLAUSIBLE_STRAND:
                # a centimetre export read as metres: 10-20 m strands ran without a word
                warnings.warn(f"{g['file']}: strands up to {longest:.3g} m long; if the file is in centimetres, "
                              f"set groom.scale = 0.01", UserWarning, stacklevel=2)
        count = groom.strand_count
        if g["max_strands"] and count > g["max_strands"]:
            groom = groom.subset(np.arange(0, count, math.ceil(count / g["max_strands"])))
        return groom

    def bind_surface(self, groom, head_rest=None):
        """Bind the groom's roots to the scalp mesh of ``[groom.surface]``, or None when it has no file.

        Args:
            groom: the guide strands (``build_groom``), in the head frame.
            head_rest: 4x4 head pose at time 0 (the groom's frame in the world), identity when None.

        Returns:
            ``(groom, binding)``: the groom with each strand moved so that its root lies on the scalp at rest, and
            the :class:`hairwarp.surface.ScalpBinding`; or None.

        Raises:
            UsdFileError: the stage or the prim cannot be read. SurfaceError: a root is farther than
                ``max_distance`` from the scalp.
        """
        from dataclasses import replace

        from hairwarp.io.usd_anim import read_surface_track
        from hairwarp.surface import ScalpBinding

        cfg = self._data["groom"]["surface"]
        if cfg["file"] is None:
            return None
        H = np.eye(4) if head_rest is None else np.asarray(head_rest, dtype=np.float64)
        from hairwarp.io.usd_common import UsdFileError

        try:
            track, faces = read_surface_track(cfg["file"], cfg["prim"], interpolation=cfg["interpolation"])
        except UsdFileError as exc:  # name the scene's key too
            raise UsdFileError(f"{self._label}: groom.surface.prim: {exc}") from None
        roots = groom.roots() @ H[:3, :3].T + H[:3, 3]
        binding = ScalpBinding(track, faces, roots, head_rest=H, max_distance=cfg["max_distance"],
                               where=f"{self._label}: groom.surface ({cfg['file']}: {cfg['prim']})")
        motion = self._data["head"]["motion"]
        if motion["kind"] != "usd" and binding.animated:  # the roots then ride on the head (``hairwarp.Simulation``)
            warnings.warn(f"{self._label}: groom.surface: {cfg['file']} animates {cfg['prim']}, but head.motion "
                          f"({motion['kind']}) does not follow it: the roots ride on the head from the scalp's pose "
                          f"at time 0, as its collider does (head.motion.kind = \"usd\" follows the stage's "
                          f"animation)", stacklevel=2)
        local = binding.offset @ H[:3, :3]  # world offsets into the head frame
        return replace(groom, strands=[a + d for a, d in zip(groom.strands, local)]), binding

    def summary(self) -> str:
        """A few lines describing the scene (``hairwarp info scene.toml``)."""
        d = self._data
        sim, g, s, h, w = d["sim"], d["groom"], d["strands"], d["head"], d["wind"]
        lines = [f"scene      {self.name}" + (f" - {d['scene']['description']}" if d["scene"]["description"] else "")]
        if self.source is not None:
            lines.append(f"file       {self.source}")
        substeps = f"{sim['substeps']} substep" + ("s" if sim["substeps"] != 1 else "")
        lines.append(f"time       {sim['frames']} frames at {sim['fps']:g} fps = {sim['frames'] / sim['fps']:.3g} s, "
                     f"{substeps} (dt = {self.step_dt * 1e3:.3g} ms), {sim['integrator']}, device {sim['device']}")
        if g["generator"] == "scalp":
            made = len(self.build_groom().strands)
            asked = f" ({g['count']} asked: what the root grid holds)" if made != g["count"] else ""
            lines.append(f"groom      scalp generator: {made} guides{asked} x {g['length']:g} m, "
                         f"{sim['segments']} segments each")
        else:
            cut = f", at most {g['max_strands']} strands" if g["max_strands"] else ""
            suffix = Path(g["file"] or "").suffix.lower()
            up = g["up_axis"] or {".tfx": "Y (the .tfx default)", ".hair": "Z (the .hair default)"}.get(suffix,
                                                                                                      "the stage's")
            lines.append(f"groom      file {g['file']} (up {up}, scale {g['scale']:g}{cut}): "
                         f"{len(self.build_groom().strands)} guides, {sim['segments']} segments per guide")
        if g["hold_shape"]:
            lines[-1] += ", held as drawn under gravity"
        if g["surface"]["file"] is not None:
            lines.append(f"roots      on the scalp mesh {g['surface']['prim']} of {g['surface']['file']} (each on its "
                         f"triangle's frame)")
        lines.append(f"strands    radius {s['radius']:g} m, density {s['density']:g} kg/m^3, "
                     f"bend {s['bend_stiffness']:g} N m^2, damping {s['damping']:g} N m^2 s, drag {s['drag']:g}")
        lines.append(f"head       {h['shape']}" + (f" at {_fmt(h['center'])} radii {_fmt(h['radii'])}"
                                                  if h["center"] is not None and h["shape"] != "none" else "")
                     + f", motion {self.head_motion()!r}")
        lk, ia, dn, out = d["links"], d["interactions"], d["dense"], d["output"]
        if lk["enabled"]:
            lines.append(f"links      {lk['neighbours']} a segment within {lk['radius']:g} m, {lk['stiffness']:g} N/m "
                         f"between 1 cm segments, break at {lk['break_length']:g} m, response {lk['response']}")
        if ia["enabled"]:
            lines.append(f"contacts   hair against hair below {ia['threshold']:g} m, {ia['stiffness']:g} N/m "
                         f"(vertex-face at 1 cm of hair), friction {ia['friction']:g}, response {ia['response']}")
        amount = (f"{dn['density']:g} per m^2 of scalp" if dn["density"] is not None
                  else f"{dn['count']} strands" if dn["count"] else "none")
        lines.append(f"dense      {amount}" + (f", {dn['basis']} curves" if amount != "none" else ""))
        lines.append(f"output     {out['up_axis']} up, {out['meters_per_unit']:g} m per unit, from frame "
                     f"{out['start_frame']}, {out['layout']} layout, {out['writer']} writer"
                     + (", guides" if out["guides"] else "") + (", preview" if out["preview"] else ""))
        for c in d["colliders"]:
            what = {"sphere": f"radius {c['radius']}", "capsule": f"radius {c['radius']}, half height "
                    f"{c['half_height']}", "ellipsoid": f"radii {_fmt(c['radii'])}", "plane": "",
                    "mesh": f"{c['file']}", "usd": f"{c['file']}" + (f": {c['prim']}" if c["prim"] else "")}
            where = "" if c["kind"] == "usd" else f", attached to the {c['attach']}"
            lines.append(f"collider   {c['name']}: {c['kind']} {what[c['kind']]}".rstrip() + where)
        if any(w["velocity"]):
            lines.append(f"wind       {_fmt(w['velocity'])} m/s from {w['start']:g} s to {_fmt(w['end'])} s")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, source={str(self.source) if self.source else None!r})"


# ----------------------------------------------------------------------------------------------
# overrides

_PART_RE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?$")


def _split_path(path: str) -> list[tuple[str, int | None]]:
    parts = []
    for piece in path.split("."):
        m = _PART_RE.match(piece.strip())
        if not m:
            raise KeyError(path)
        parts.append((m.group(1), int(m.group(2)) if m.group(2) is not None else None))
    return parts


def _parse_value(text: str):
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text.strip()


def _override_keys(overrides) -> set[str]:
    """The key paths that ``key.path=value`` overrides set."""
    return {text.split("=", 1)[0].strip() for text in overrides if "=" in text}


def _unread_motion_overrides(kind: str, keys: set[str]) -> list[tuple[str, str]]:
    """Errors for the overrides of ``[head.motion]`` keys that ``kind`` does not read (``-s head.motion.distance=0.05``
    on a turn would change nothing). The scene file's own keys for other kinds stay allowed: overriding ``kind``
    alone must work on any scene."""
    read = set(_motion.MOTION_KEYS[kind])
    errors = []
    for key in sorted(keys):
        leaf = key.removeprefix("head.motion.")
        if key.startswith("head.motion.") and "." not in leaf and "[" not in leaf and leaf != "kind" \
                and leaf not in read:
            kinds = [k for k, keys in _motion.MOTION_KEYS.items() if leaf in keys]
            if kinds:
                fix = "drop this override" if "head.motion.kind" in keys else "set head.motion.kind too"
                errors.append((key, f"is read by kind = {' or '.join(repr(k) for k in kinds)} only "
                                    f"(kind is {kind!r}); {fix}"))
    return errors


def _switch_motion_kind(raw: dict, keys: set[str]):
    """An override of ``head.motion.kind`` drops the file's ``[head.motion]`` keys the new kind does not read:
    ``-s 'head.motion.kind="still"'`` holds the head of a keyframed scene still (its ``[[head.motion.keys]]`` were
    refused as keys of another kind, and no override can remove a table). Keys the overrides set themselves stay,
    and are reported if the kind does not read them."""
    motion = raw.get("head", {}).get("motion") if isinstance(raw.get("head"), dict) else None
    if "head.motion.kind" not in keys or not isinstance(motion, dict):
        return
    read = set(_motion.MOTION_KEYS.get(motion.get("kind"), ())) | {"kind"}
    for name in [k for k in motion if k not in read and f"head.motion.{k}" not in keys]:
        del motion[name]


def _switch_dense_amount(raw: dict, keys: set[str]):
    """An override of ``dense.density`` replaces the file's ``dense.count`` (0), and one of ``dense.count`` the file's
    density: ``-s dense.density=20000`` on a scene that gives a count asks for that density."""
    dense = raw.get("dense")
    if not isinstance(dense, dict):
        return
    if "dense.density" in keys and "dense.count" not in keys:
        dense.pop("count", None)
    elif "dense.count" in keys and "dense.density" not in keys:
        dense.pop("density", None)


def _switch_collider_kinds(raw: dict, keys: set[str]):
    """An override of a collider's ``kind`` drops the file's keys of that collider that the new kind does not read
    (``-s 'colliders[0].kind="mesh"' -s colliders[0].file=...`` turns a capsule into a mesh where it was; its radius
    goes). Keys the overrides set themselves stay, and are reported if the kind does not read them."""
    colliders = raw.get("colliders")
    for key in keys:
        match = re.fullmatch(r"colliders\[(\d+)\]\.kind", key)
        if not match or not isinstance(colliders, list) or int(match.group(1)) >= len(colliders):
            continue
        i = int(match.group(1))
        table = colliders[i]
        read = set(_COLLIDER_KEYS.get(table.get("kind"), ())) | _COLLIDER_COMMON
        for name in [k for k in table if k not in read and f"colliders[{i}].{k}" not in keys]:
            del table[name]


def _switch_groom_source(raw: dict, keys: set[str]):
    """An override that names the groom's source (``groom.file`` or ``groom.generator``) replaces the file's other
    source: its keys go (``-s groom.file=...`` on a generated scene reads that file instead of raising "give either
    generator or file"). Keys of the other source that the overrides set themselves stay, and are reported."""
    groom = raw.get("groom")
    if not isinstance(groom, dict):
        return
    if "groom.file" in keys and "groom.generator" not in keys:
        drop = ("generator", *_SCALP_KEYS)
    elif "groom.generator" in keys and "groom.file" not in keys:
        drop = ("file", *_FILE_KEYS)
    else:
        return
    for key in drop:
        if f"groom.{key}" not in keys:
            groom.pop(key, None)


def _apply_override(raw: dict, text: str):
    """Set ``key.path=value`` in ``raw``; raises ValueError((path, message)) when malformed."""
    if "=" not in text:
        raise ValueError((text, "override must look like key.path=value"))
    key, value = (s.strip() for s in text.split("=", 1))
    try:
        parts = _split_path(key)
    except KeyError:
        raise ValueError((key, "override key must be a dotted path such as sim.frames or head.motion.keys[0].time")) \
            from None
    node = raw
    for depth, (name, index) in enumerate(parts):
        last = depth == len(parts) - 1
        where = ".".join(f"{n}[{i}]" if i is not None else n for n, i in parts[: depth + 1])
        if index is None:
            if last:
                node[name] = _parse_value(value)
                return
            node = node.setdefault(name, {})
        else:
            items = node.setdefault(name, [])
            if not isinstance(items, list) or index > len(items):
                raise ValueError((where, f"index {index} is past the end of the array ({len(items)} tables)"))
            if index == len(items):
                items.append({})
            node = items[index]
        if not isinstance(node, dict):
            raise ValueError((where, f"is not a table, cannot set {key}"))


def schema_doc() -> str:
    """The schema as text: one line per key with type, default, range, unit and meaning."""
    out = []

    def walk(sec: Section, path: str):
        for name, spec in sec.fields.items():
            sub = _join(path, name)
            if isinstance(spec, Section):
                out.append(f"[{sub}]  {spec.doc}")
                walk(spec, sub)
            elif isinstance(spec, ArrayOf):
                out.append(f"[[{sub}]]  {spec.doc}")
                walk(spec.section, sub)
            else:
                out.append(f"  {sub} = {spec.describe()}  -- {spec.doc}")

    walk(_ROOT, "")
    return "\n".join(out)
