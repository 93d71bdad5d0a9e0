"""What the USD readers and writers of hairwarp share: the stage layout, unit and axis conversion, ``Vt`` copies,
curve and mesh arrays, and opening a stage with an error that names the file.

Layout of every stage written by hairwarp::

    /World                      Xform, kind "component", the stage's defaultPrim
        /Hair/<name>            BasisCurves, time-sampled points, velocities and extent
        /Colliders/<name>       Mesh, time-sampled xformOp:transform (and points, if animated)

Units and axes. The simulator works in metres, Z up. A writer records the stage's ``upAxis`` and
``metersPerUnit`` and converts what it is given into them: positions, velocities and widths are divided by
``metersPerUnit``, and for a Y-up stage a Z-up point ``(x, y, z)`` is stored as ``(x, z, -y)``. Readers undo
both, so they always return metres, Z up, in world space (a Y-up point ``(x, y, z)`` becomes ``(x, -z, y)``,
a rotation of +90 degrees about x).

Matrices. hairwarp passes 4x4 numpy matrices in the column-vector convention, ``p_world = M @ [p, 1]``.
USD uses row vectors, ``p_world = [p, 1] @ M_usd``, so writers store ``M_usd = M.T`` and readers return
``M_usd.T``.

``pxr`` is imported inside the functions that need it, so importing this module does not load USD.
"""

from __future__ import annotations

import ctypes
import math
import os
import re
from pathlib import Path

import numpy as np

USD_SUFFIXES = (".usd", ".usda", ".usdc")
ROOT_PATH = "/World"
HAIR_PATH = ROOT_PATH + "/Hair"
COLLIDERS_PATH = ROOT_PATH + "/Colliders"

DEFAULT_WIDTHS = (1.0e-4, 2.0e-5)
"""Root and tip diameter [m] when none are given: a thick human hair tapering to a fine tip."""

GUIDE_COLOR = (0.95, 0.45, 0.10)
"""displayColor of guide curves (orange), so they stand out from dense hair in a viewport."""
DENSE_COLOR = (0.36, 0.22, 0.12)
"""displayColor of dense curves (mid brown)."""
MESH_COLOR = (0.70, 0.70, 0.70)
"""displayColor of collider meshes (light grey)."""

# Y-up stage coordinates from Z-up coordinates: (x, y, z) -> (x, z, -y), a rotation of -90 degrees about x.
_Z_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class UsdFileError(ValueError):
    """A USD file that cannot be opened, read or written as asked; the message names the file."""


def _conversion(up_axis: str, meters_per_unit: float) -> np.ndarray:
    """3x3 matrix taking metres, Z up, to stage units on a stage with ``up_axis`` and ``meters_per_unit``."""
    rot = _Z_TO_Y if up_axis == "Y" else np.eye(3)
    return rot / meters_per_unit


def _default_permissions(path) -> None:
    """Give a file made by mkstemp (mode 0600) the mode an ordinary new file would get under the current umask."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def _reload_if_open(path: Path) -> None:
    """Make a layer of this path that is still open in the process (e.g. an earlier cache) read the new file."""
    from pxr import Sdf

    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)


_DIRECT_COPY: bool | None = None
"""Whether ``Vt.Vec3fArray`` exposes its own storage through the buffer protocol (checked once, see _vec3f)."""


def _vt_address(array) -> int:
    """Address of the first element of a Vt array, through its (read-only) buffer."""
    return np.frombuffer(memoryview(array).cast("B"), dtype=np.uint8).ctypes.data


def _direct_copy_works() -> bool:
    """Check once that bytes copied through the buffer of a fresh ``Vt.Vec3fArray`` land in the array itself."""
    from pxr import Vt

    probe = np.arange(12, dtype=np.float32).reshape(4, 3) + np.float32(0.5)
    out = Vt.Vec3fArray(len(probe))
    try:
        ctypes.memmove(_vt_address(out), probe.ctypes.data, probe.nbytes)
    except (TypeError, ValueError, BufferError):
        return False
    return bool(np.array_equal(np.array(out, dtype=np.float32), probe))


def _vec3f(values: np.ndarray, out=None):
    """A ``Vt.Vec3fArray`` holding a copy of an (N, 3) array; into ``out`` (a ``Vt.Vec3fArray`` of N elements this
    module made, which nothing reads any more) when given and the direct copy works, else into a fresh one.

    ``Vt.Vec3fArray.FromNumpy`` converts element by element (about 0.6 GB/s); this allocates the array and copies
    the bytes with one ``memmove`` into its storage (2.4x faster for 100 MB in a fresh process, 14x with the writer
    process's allocator settings). The storage is reached through the array's read-only buffer; writing it is safe
    because the array was just allocated here and shares its storage with nothing. Whether the buffer is the
    storage is checked once against a read-back; if not, FromNumpy is used.
    """
    global _DIRECT_COPY
    from pxr import Vt

    a = np.ascontiguousarray(values, dtype=np.float32)
    if _DIRECT_COPY is None:
        _DIRECT_COPY = _direct_copy_works()
    if not _DIRECT_COPY or a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        return Vt.Vec3fArray.FromNumpy(a)
    if out is None or len(out) != len(a):
        out = Vt.Vec3fArray(len(a))
    ctypes.memmove(_vt_address(out), a.ctypes.data, a.nbytes)
    return out


def _column_bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis minimum and maximum of an (N, 3) array, column by column (several times faster than a reduction
    over axis 0 of an (N, 3) array); a NaN shows up in them."""
    return np.array([a[:, i].min() for i in range(3)]), np.array([a[:, i].max() for i in range(3)])


def _extent(lo: np.ndarray, hi: np.ndarray, half_width: float) -> np.ndarray:
    """The (2, 3) float32 extent of points with per-axis bounds ``lo``, ``hi``, widened by ``half_width``."""
    return np.stack([lo - half_width, hi + half_width]).astype(np.float32)


def _check_suffix(path: Path) -> None:
    if path.suffix.lower() not in USD_SUFFIXES:
        raise UsdFileError(f"{path}: USD files must end in one of {', '.join(USD_SUFFIXES)}, not {path.suffix!r}")


def _check_stage_units(path, up_axis: str, meters_per_unit: float) -> None:
    if up_axis not in ("Y", "Z"):
        raise UsdFileError(f"{path}: up_axis must be 'Y' or 'Z', not {up_axis!r}")
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0.0):
        raise UsdFileError(f"{path}: meters_per_unit must be a positive number, not {meters_per_unit!r}")


def _vertex_widths(counts: np.ndarray, widths, where: str) -> tuple[np.ndarray, str]:
    """Per-vertex or constant widths [m] from a scalar, a (root, tip) pair or a per-vertex array.

    Returns the widths and their USD interpolation ("constant" or "vertex"). A pair is tapered linearly in the
    vertex index from the root (vertex 0) to the tip of every curve.
    """
    total = int(counts.sum())
    w = np.asarray(DEFAULT_WIDTHS if widths is None else widths, dtype=np.float64)
    if w.ndim == 0:
        out, interp = w.reshape(1), "constant"
    elif w.shape == (2,) and total != 2:
        ends = np.repeat(np.cumsum(counts), counts)
        k = np.arange(total) - (ends - np.repeat(counts, counts))
        frac = k / np.maximum(np.repeat(counts, counts) - 1, 1)
        out, interp = w[0] + (w[1] - w[0]) * frac, "vertex"
    elif w.shape == (total,):
        out, interp = w, "vertex"
    else:
        raise UsdFileError(
            f"{where}: widths must be a number, a (root, tip) pair or one value per vertex ({total}), "
            f"not an array of shape {w.shape}"
        )
    if not (np.all(np.isfinite(out)) and np.all(out >= 0.0)):
        raise UsdFileError(f"{where}: widths must be finite and not negative")
    return out, interp


def _new_stage(layer_path: str | None, *, up_axis: str, meters_per_unit: float, doc: str, suffix: str = ".usdc"):
    """Create a layer (a file, or in memory with the format of ``suffix`` when ``layer_path`` is None) and its stage
    with the /World root and the stage metadata set; returns (layer, stage)."""
    from pxr import Kind, Sdf, Usd, UsdGeom

    import hairwarp

    layer = Sdf.Layer.CreateAnonymous(f"hairwarp{suffix}") if layer_path is None else Sdf.Layer.CreateNew(layer_path)
    if layer is None:
        raise UsdFileError(f"{layer_path}: cannot create a USD layer")
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    layer.documentation = doc
    layer.customLayerData = {"creator": f"hairwarp {hairwarp.__version__}"}
    root = UsdGeom.Xform.Define(stage, ROOT_PATH)
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    stage.SetDefaultPrim(root.GetPrim())
    UsdGeom.Xform.Define(stage, HAIR_PATH)
    return layer, stage


GROOM_API = "GroomAPI"
"""The API schema Unreal's USD importer looks for to take a prim as a groom (it reads the curves under it, their
points, widths and every ``primvars:groom_*``). usd-core does not define it, so it is applied by name (an entry of
the prim's ``apiSchemas`` metadata), which is all the importer checks."""


def _define_curves(stage, prim_path: str, counts: np.ndarray, widths: np.ndarray, widths_interp: str, *, basis: str,
                   kind: str, purpose: str, root_uv: np.ndarray | None = None, strand_ids: np.ndarray | None = None):
    """Define a BasisCurves prim with its static topology, widths, colour, purpose and groom primvars.

    Besides the UsdGeom attributes every client reads, the prim carries what Unreal's groom importer reads (one
    value per curve, ``uniform``): ``primvars:groom_id`` (int, the strand's id), ``primvars:groom_guide`` (int, 1
    on simulation guides: curves of purpose "guide"), and with ``root_uv`` both ``primvars:groom_root_uv`` (float2)
    and the standard ``primvars:st`` (texCoord2f) that renderers, Blender and Houdini read; the prim and its
    parent get the ``GroomAPI`` schema (see :data:`GROOM_API`).
    """
    from pxr import Sdf, UsdGeom, Vt

    curves = UsdGeom.BasisCurves.Define(stage, prim_path)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
    if basis == "linear":
        curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    else:
        curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
        curves.CreateBasisAttr(UsdGeom.Tokens.catmullRom)
        curves.CreateWrapAttr(UsdGeom.Tokens.pinned)
    curves.CreateWidthsAttr(Vt.FloatArray.FromNumpy(widths.astype(np.float32)))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant if widths_interp == "constant" else UsdGeom.Tokens.vertex)
    curves.CreatePurposeAttr(purpose)
    color = GUIDE_COLOR if kind == "guides" else DENSE_COLOR
    curves.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([color]))
    prim = curves.GetPrim()
    prim.CreateAttribute("hairwarp:curveKind", Sdf.ValueTypeNames.Token, custom=True,
                         variability=Sdf.VariabilityUniform).Set(kind)
    n = len(counts)
    api = UsdGeom.PrimvarsAPI(prim)
    ids = np.arange(n, dtype=np.int32) if strand_ids is None else np.asarray(strand_ids, dtype=np.int32)
    api.CreatePrimvar("groom_id", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(Vt.IntArray.FromNumpy(ids))
    guide = np.full(n, 1 if purpose == "guide" else 0, dtype=np.int32)
    api.CreatePrimvar("groom_guide", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(
        Vt.IntArray.FromNumpy(guide))
    if root_uv is not None:
        uv = np.ascontiguousarray(root_uv, dtype=np.float32).reshape(n, 2)
        api.CreatePrimvar("groom_root_uv", Sdf.ValueTypeNames.Float2Array, UsdGeom.Tokens.uniform).Set(
            Vt.Vec2fArray.FromNumpy(uv))
        api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.uniform).Set(
            Vt.Vec2fArray.FromNumpy(uv))
    # The parent too: Unreal then imports the curves under it as one groom (dense hair and its guides together).
    for p in (prim, prim.GetParent()):
        p.AddAppliedSchema(GROOM_API)  # by name; a no-op when already there
    return curves


def _vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals of a triangle mesh: the area-weighted sum of the normals of the faces
    around each vertex, in the winding's (right-handed) sense; a vertex on no face gets (0, 0, 1)."""
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = np.zeros_like(p)
    if len(f):
        face_n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])  # length = twice the area
        for k in range(3):
            np.add.at(n, f[:, k], face_n)
    norm = np.linalg.norm(n, axis=1)
    out = np.where(norm[:, None] > 0.0, n / np.where(norm > 0.0, norm, 1.0)[:, None], (0.0, 0.0, 1.0))
    return out.astype(np.float32)


# One diagnostic of usd-core: "Error in 'pxrInternal_v0_26_11__pxrReserved__::UsdStage::Open' at line 1287 in file
# /opt/USD/pxr/usd/usd/stage.cpp : 'Failed to open layer @x.usdc@'" (also "Coding Error", "Runtime Error", "Warning").
_TF_ERROR_RE = re.compile(r"^\s*[A-Za-z ]*(?:Error|Warning) in '[^']*' at line \d+ (?:in|of) file \S+ : '(.*)'\s*$")
# What is left of usd-core's internals anywhere else in a message: the versioned namespace and the source place.
_TF_NAMESPACE_RE = re.compile(r"pxrInternal_v\d+_\d+(?:_\d+)?__pxrReserved__::")
_TF_PLACE_RE = re.compile(r"\s*\bat line \d+ (?:in|of) file \S+(?: :)?")
_TF_LINE_RE = re.compile(r"\s*\bat line \d+\b")  # cut only after usd-core's namespace: other messages cite lines


def clean_usd_text(text: str) -> str:
    """``text`` on one line without usd-core's internals: each ``Error in 'pxrInternal_...::UsdStage::Open' at
    line 1287 in file ... : 'what'`` becomes ``what`` (repeats dropped, joined by ``; ``), and any other mention of
    the versioned namespace or a C++ source line is cut. Every USD error shown to a user goes through this."""
    lines = [ln for ln in str(text).strip().splitlines() if ln.strip()]
    texts = [m.group(1) if (m := _TF_ERROR_RE.match(ln)) else ln.strip() for ln in lines]
    texts = [_TF_LINE_RE.sub("", _TF_NAMESPACE_RE.sub("", t)) if _TF_NAMESPACE_RE.search(t) else t for t in texts]
    texts = [_TF_PLACE_RE.sub("", t).strip() for t in texts]
    return "; ".join(dict.fromkeys(t for t in texts if t))


def usd_error_text(exc: BaseException) -> str:
    """The message of a usd-core error for a user (:func:`clean_usd_text`), or the exception's type name."""
    return clean_usd_text(str(exc)) or type(exc).__name__


def check_usd_path(path) -> None:
    """A UsdFileError naming ``path`` when USD cannot take it: USD takes paths as UTF-8, and a name with bytes that
    are not (an old Latin-1 file name) failed with the codec's message, naming nothing."""
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        raise UsdFileError(f"{os.fsencode(path).decode('utf-8', 'backslashreplace')}: USD takes UTF-8 file names "
                           f"only; rename it") from None


def _open_stage(path):
    """Open a stage read-only, raising UsdFileError naming the file when it is missing or unreadable."""
    from pxr import Tf, Usd

    path = Path(path)
    if path.is_dir():
        raise UsdFileError(f"{path}: is a folder; name the USD file in it")
    if not path.is_file():
        raise UsdFileError(f"{path}: no such file")
    check_usd_path(path)
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as e:
        raise UsdFileError(f"{path}: cannot be opened as USD ({usd_error_text(e)})") from e
    if stage is None:
        raise UsdFileError(f"{path}: cannot be opened as USD")
    return stage


def stage_units(stage) -> tuple[str, float]:
    """The stage's up axis ("Y" or "Z") and metres per unit, or a UsdFileError naming the file and the value (a
    negative ``metersPerUnit`` mirrored the stage without a word, 0 made every point NaN, and an X up axis was read
    as Z)."""
    from pxr import UsdGeom

    where = stage.GetRootLayer().identifier
    up = str(UsdGeom.GetStageUpAxis(stage))
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    if up not in ("Y", "Z"):
        raise UsdFileError(f"{where}: upAxis = {up!r}; USD stages are Y or Z up")
    if not (math.isfinite(mpu) and mpu > 0.0):
        raise UsdFileError(f"{where}: metersPerUnit = {mpu!r}; it must be a finite number > 0 (0.01 for centimetres)")
    return up, mpu


def _stage_to_metres_z(stage) -> np.ndarray:
    """3x3 matrix taking this stage's units and up axis to metres, Z up."""
    return np.linalg.inv(_conversion(*stage_units(stage)))


def _prims(stage, schema):
    from pxr import Usd

    for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
        if prim.IsA(schema):
            yield prim


def _first_time(attr):
    from pxr import Usd

    samples = attr.GetTimeSamples()
    return Usd.TimeCode(samples[0]) if samples else Usd.TimeCode.Default()


def _apply_linear(p: np.ndarray, a: np.ndarray, b=None) -> np.ndarray:
    """Row vectors ``p @ a + b``, skipping an identity ``a`` and a zero ``b``.

    einsum stays fast for (N, 3) @ (3, 3), where a threaded BLAS call can be ten times slower on a busy machine.
    """
    out = p if np.array_equal(a, np.eye(3)) else np.einsum("ij,jk->ik", p, a)
    if b is not None and np.any(b):
        out = out + b
    return out


def _world_points(points, xform_cache, prim, conv: np.ndarray) -> np.ndarray:
    """Local points (stage units) -> world metres, Z up, float64, via the prim's local-to-world matrix."""
    m = np.array(xform_cache.GetLocalToWorldTransform(prim), dtype=np.float64)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    # Row vectors: world = p @ M[:3, :3] + M[3, :3]; then metres Z up = world @ conv.T.
    return _apply_linear(p, m[:3, :3] @ conv.T, m[3, :3] @ conv.T)


def _curve_arrays(prim, time, xform_cache, conv, path) -> tuple[np.ndarray, np.ndarray]:
    from pxr import UsdGeom

    curves = UsdGeom.BasisCurves(prim)
    counts = np.asarray(curves.GetCurveVertexCountsAttr().Get(time) or [], dtype=np.int64)
    pts = curves.GetPointsAttr().Get(time)
    pts = np.zeros((0, 3)) if pts is None else np.asarray(pts)
    if counts.sum() != len(pts):
        raise UsdFileError(f"{path}: {prim.GetPath()} has {len(pts)} points but its curveVertexCounts add up "
                           f"to {int(counts.sum())}")
    return _world_points(pts, xform_cache, prim, conv), counts


def _mesh_arrays(prim, time, xform_cache, conv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World vertices [m, Z up], triangles (a fan per polygon) and the 4x4 column-convention world matrix."""
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(mesh.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
    tris = _triangles(mesh, time)
    m_usd = np.array(xform_cache.GetLocalToWorldTransform(prim), dtype=np.float64)
    c = np.eye(4)
    c[:3, :3] = conv
    world = c @ m_usd.T @ np.linalg.inv(c)
    return _world_points(pts, xform_cache, prim, conv), tris, world


def _triangles(mesh, time) -> np.ndarray:
    """(F, 3) int64 triangles of a UsdGeom.Mesh's faces at ``time``, a fan per polygon, in the prim's winding."""
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if counts.size and np.all(counts == 3):
        return idx.reshape(-1, 3)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    fan = [[idx[s], idx[s + j], idx[s + j + 1]] for s, n in zip(starts, counts, strict=True) for j in range(1, n - 1)]
    return np.array(fan, dtype=np.int64).reshape(-1, 3)


def _time_samples(stage) -> list[float]:
    from pxr import UsdGeom

    times = set()
    for prim in _prims(stage, UsdGeom.BasisCurves):
        times.update(UsdGeom.BasisCurves(prim).GetPointsAttr().GetTimeSamples())
    for prim in _prims(stage, UsdGeom.Mesh):
        times.update(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples())
        for op in UsdGeom.Xformable(prim).GetOrderedXformOps():
            times.update(op.GetAttr().GetTimeSamples())
    return sorted(times)


def _unique_names(prims) -> list[str]:
    names = [p.GetName() for p in prims]
    if len(set(names)) == len(names):
        return names
    return [str(p.GetPath()) for p in prims]


def _human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024.0 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} GiB"
