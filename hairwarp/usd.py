"""USD input and output: animation caches of hair curves and collider meshes, static grooms, animated colliders.

Layout of every stage written here::

    /World                      Xform, kind "component", the stage's defaultPrim
        /Hair/<name>            BasisCurves, time-sampled points, velocities and extent
        /Colliders/<name>       Mesh, time-sampled xformOp:transform (and points, if animated)

Units and axes. The simulator works in metres, Z up. A writer records the stage's ``upAxis`` and
``metersPerUnit`` and converts what it is given into them: positions, velocities and widths are divided by
``metersPerUnit``, and for a Y-up stage a Z-up point ``(x, y, z)`` is stored as ``(x, z, -y)``. Readers undo
both, so :func:`read_curves` and :func:`read_frames` always return metres, Z up, in world space (a Y-up point
``(x, y, z)`` becomes ``(x, -z, y)``, a rotation of +90 degrees about x).

Matrices. hairwarp passes 4x4 numpy matrices in the column-vector convention, ``p_world = M @ [p, 1]``.
USD uses row vectors, ``p_world = [p, 1] @ M_usd``, so the writer stores ``M_usd = M.T`` and the readers
return ``M_usd.T``.

Writing. :class:`CacheWriter` writes into a temporary file beside the destination whose name keeps the
destination's suffix (USD chooses the file format from it), and renames it into place on :meth:`CacheWriter.close`.
Binary layers (``.usdc``, ``.usd``) are saved after every frame: the crate format appends the new samples, so
memory stays flat however long the cache is, and a process that dies leaves the frames written so far in the
temporary file. ``.usda`` layers are text and are saved once, at close.

Cost of a frame. The writer takes float32, C-contiguous (N, 3) arrays without copying them (a Z-up, metre stage);
the time goes to the finiteness and extent checks, to building the ``Vt`` arrays that USD stores (one ``memmove``
into a fresh array, see :func:`_vec3f`; usd-core's own ``FromNumpy`` copies element by element at about 0.6 GB/s)
and to the crate's write in ``Sdf.Layer.Save``, bound by the disk (0.3-1.4 GB/s here);
:attr:`CacheWriter.timings` adds them up per phase. Saving every few frames instead of every frame was measured too,
and is slower for large frames (the unsaved samples pile up in memory), so it is not offered.

Background writing. :class:`BackgroundCacheWriter` (``output.writer = "background"`` in a scene) checks each frame
in the caller, copies it into shared memory and returns; a second process converts, authors and saves it, so with a
core to spare a frame costs about the larger of simulating it and writing it instead of their sum. Same file, same
guarantees (every frame of a binary layer saved as it comes). Without a free core it only adds the copy and a second
usd-core, which is why it is not the default; :func:`hairwarp.benchmarks.dense.bench_dense_pipeline` measures both.

``pxr`` is imported inside the functions that need it, so ``import hairwarp`` does not load USD.
"""

from __future__ import annotations

import atexit
import ctypes
import os
import sys
import tempfile
import time
import weakref
from pathlib import Path

import numpy as np

__all__ = [
    "BackgroundCacheWriter",
    "CacheWriter",
    "UsdFileError",
    "background_supported",
    "bench_usd_write",
    "describe",
    "mesh_motion",
    "read_animated_collider",
    "read_animated_mesh",
    "read_curves",
    "read_frames",
    "write_curves",
]

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


def _vec3f(values: np.ndarray):
    """A ``Vt.Vec3fArray`` holding a copy of an (N, 3) array.

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


def _new_stage(layer_path: str, *, up_axis: str, meters_per_unit: float, doc: str):
    """Create a layer and stage with the /World root and the stage metadata set; returns (layer, stage)."""
    from pxr import Kind, Sdf, Usd, UsdGeom

    import hairwarp

    layer = Sdf.Layer.CreateNew(layer_path)
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


def _define_curves(stage, prim_path: str, counts: np.ndarray, widths: np.ndarray, widths_interp: str, *, basis: str,
                   kind: str, purpose: str):
    """Define a BasisCurves prim with its static topology, widths, colour and purpose."""
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
    curves.GetPrim().CreateAttribute("hairwarp:curveKind", Sdf.ValueTypeNames.Token, custom=True,
                                     variability=Sdf.VariabilityUniform).Set(kind)
    return curves


class CacheWriter:
    """Writes a time-sampled USD animation cache of hair curves and collider meshes.

    Points are given in world metres, Z up, and stored at the time code ``frame``; ``timeCodesPerSecond`` and
    ``framesPerSecond`` are both ``fps``, so velocities are per second. Usage::

        with CacheWriter("out/hair.usdc", fps=24) as cache:
            cache.add_curves("dense", counts, widths=(1e-4, 2e-5), basis="catmullRom")
            cache.add_mesh("head", vertices, faces)
            for frame in range(48):
                cache.write_frame(frame, {"dense": (points, velocities)}, xforms={"head": head_matrix})

    An exception inside the ``with`` block still saves the frames written so far and renames the file into place;
    the exception then propagates. :class:`BackgroundCacheWriter` has the same interface and writes in a second
    process.

    Args:
        path: destination, ending in .usd, .usda or .usdc; its folder is created if missing.
        fps: frames per second of the cache.
        start_frame: the first frame that may be written; also the start and end time code of a cache with no frame.
        meters_per_unit: stage unit, in metres.
        up_axis: "Z" (the simulator's) or "Y"; data are rotated into it.
        comment: appended to the layer's documentation string.

    Attributes:
        timings: seconds spent in :meth:`write_frame` so far, per phase: ``check`` (validation, unit conversion,
            extent), ``convert`` (numpy to ``Vt`` arrays), ``set`` (authoring the samples), ``save`` (crate writes).
    """

    _EXTENTS_IN_CALLER = True
    """Whether :meth:`write_frame` computes the extents while checking (else :meth:`_author_frame` does)."""

    def __init__(self, path, *, fps: float, start_frame: int = 0, meters_per_unit: float = 1.0, up_axis: str = "Z",
                 comment: str = ""):
        self._setup(path, fps, start_frame, meters_per_unit, up_axis)
        self.timings = {"check": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0}
        self._prims: dict[str, dict] = {}
        self._incremental = self.path.suffix.lower() != ".usda"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=f".partial{self.path.suffix}",
                                   dir=self.path.parent)
        os.close(fd)
        _default_permissions(tmp)
        self._tmp_path = Path(tmp)
        doc = f"hairwarp animation cache: hair curves under {HAIR_PATH}, colliders under {COLLIDERS_PATH}."
        if comment:
            doc += "\n" + comment
        try:
            self._layer, self._stage = _new_stage(tmp, up_axis=up_axis, meters_per_unit=self.meters_per_unit, doc=doc)
        except Exception:
            self._tmp_path.unlink(missing_ok=True)
            raise
        self._stage.SetFramesPerSecond(self.fps)
        self._stage.SetTimeCodesPerSecond(self.fps)
        self._set_time_range()

    def _setup(self, path, fps, start_frame, meters_per_unit, up_axis) -> None:
        """Check the arguments and set what both writers keep: units, the frames written, the prims declared."""
        self.path = Path(path).absolute()
        _check_suffix(self.path)
        _check_stage_units(self.path, up_axis, meters_per_unit)
        if not (np.isfinite(fps) and fps > 0.0):
            raise UsdFileError(f"{self.path}: fps must be a positive number, not {fps!r}")
        self.fps = float(fps)
        self.start_frame = int(start_frame)
        self.up_axis = up_axis
        self.meters_per_unit = float(meters_per_unit)
        self._conv = _conversion(up_axis, self.meters_per_unit)
        self._identity = up_axis == "Z" and self.meters_per_unit == 1.0
        # Stage axis j of a converted point = coef * metres axis i (the conversion is a scaled signed permutation).
        self._columns = []
        for row in self._conv:
            i = int(np.flatnonzero(row)[0])
            self._columns.append((i, float(row[i])))
        self._frames: list[int] = []
        # name -> {"vertex_count", "half_width" (stage units), "velocities" (True once given)}
        self._curves: dict[str, dict] = {}
        # name -> {"vertex_count", "animated"}
        self._meshes: dict[str, dict] = {}
        self._closed = False

    # --- setup -----------------------------------------------------------------------------------------------

    def add_curves(self, name: str, curve_vertex_counts, *, widths=DEFAULT_WIDTHS, kind: str = "dense",
                   basis: str = "linear", purpose: str = "default") -> str:
        """Declare a BasisCurves prim ``/World/Hair/<name>``; its points are given to :meth:`write_frame`.

        Args:
            name: prim name, a valid USD identifier.
            curve_vertex_counts: vertices per curve (ints), root first in every curve.
            widths: diameter [m]: a number, a (root, tip) pair tapered linearly along every curve, or one value per
                vertex.
            kind: "dense" or "guides"; recorded in the custom attribute ``hairwarp:curveKind`` and in the
                displayColor (brown for dense hair, orange for guides).
            basis: "linear" (a polyline through the points) or "catmullRom" (cubic Catmull-Rom with wrap "pinned",
                which passes through every point, root and tip included).
            purpose: the UsdGeom purpose; "guide" hides the curves from renders and from viewports that hide guides.

        Returns:
            The prim path.
        """
        where = f"{self.path}: curves {name!r}"
        self._check_open()
        self._check_name(name, where)
        if self._frames:
            raise UsdFileError(f"{where}: curves must be added before the first frame is written")
        if kind not in ("dense", "guides"):
            raise UsdFileError(f"{where}: kind must be 'dense' or 'guides', not {kind!r}")
        if basis not in ("linear", "catmullRom"):
            raise UsdFileError(f"{where}: basis must be 'linear' or 'catmullRom', not {basis!r}")
        if purpose not in ("default", "render", "proxy", "guide"):
            raise UsdFileError(f"{where}: purpose must be default, render, proxy or guide, not {purpose!r}")
        counts = np.asarray(curve_vertex_counts)
        if counts.ndim != 1 or counts.size == 0 or not np.issubdtype(counts.dtype, np.integer):
            raise UsdFileError(f"{where}: curve_vertex_counts must be a non-empty 1-D array of ints")
        min_count = 4 if basis == "catmullRom" else 2
        if counts.min() < min_count:
            raise UsdFileError(f"{where}: every {basis} curve needs at least {min_count} vertices")
        counts = counts.astype(np.int64)
        w, interp = _vertex_widths(counts, widths, where)
        spec = {"name": name, "counts": counts, "widths": w / self.meters_per_unit, "interp": interp, "basis": basis,
                "kind": kind, "purpose": purpose}
        self._author_curves(spec)
        self._curves[name] = {"vertex_count": int(counts.sum()),
                              "half_width": 0.5 * float(w.max()) / self.meters_per_unit, "velocities": None}
        return f"{HAIR_PATH}/{name}"

    def add_mesh(self, name: str, points, face_vertex_indices, *, animated_points: bool = False) -> str:
        """Declare a triangle mesh ``/World/Colliders/<name>`` with a time-sampled transform.

        Args:
            name: prim name, a valid USD identifier.
            points: (V, 3) vertices [m] in the mesh's own frame (Z up); for an animated mesh, its rest pose.
            face_vertex_indices: (F, 3) vertex indices of the triangles.
            animated_points: the points change per frame and are given to :meth:`write_frame` in ``mesh_points``.

        Returns:
            The prim path.
        """
        where = f"{self.path}: mesh {name!r}"
        self._check_open()
        self._check_name(name, where)
        if self._frames:
            raise UsdFileError(f"{where}: meshes must be added before the first frame is written")
        pts, lo, hi = self._points(points, None, where)
        faces = np.asarray(face_vertex_indices)
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise UsdFileError(f"{where}: face_vertex_indices must be an (F, 3) array of ints")
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise UsdFileError(f"{where}: face_vertex_indices out of range for {len(pts)} points")
        spec = {"name": name, "points": pts, "extent": np.stack([lo, hi]).astype(np.float32),
                "faces": faces.astype(np.int32)}
        self._author_mesh(spec)
        self._meshes[name] = {"animated": bool(animated_points), "vertex_count": len(pts)}
        return f"{COLLIDERS_PATH}/{name}"

    def _author_curves(self, spec: dict) -> None:
        """Define the curves prim of a checked ``add_curves`` on the stage."""
        name = spec["name"]
        curves = _define_curves(self._stage, f"{HAIR_PATH}/{name}", spec["counts"], spec["widths"], spec["interp"],
                                basis=spec["basis"], kind=spec["kind"], purpose=spec["purpose"])
        self._prims[name] = {"schema": curves, "points": curves.CreatePointsAttr(), "velocities": None,
                             "extent": curves.CreateExtentAttr(), "half_width": 0.5 * float(np.max(spec["widths"]))}

    def _author_mesh(self, spec: dict) -> None:
        """Define the mesh prim of a checked ``add_mesh`` on the stage (points in stage units, float32)."""
        from pxr import Gf, UsdGeom, Vt

        if not self._stage.GetPrimAtPath(COLLIDERS_PATH):
            UsdGeom.Xform.Define(self._stage, COLLIDERS_PATH)
        faces = spec["faces"]
        mesh = UsdGeom.Mesh.Define(self._stage, f"{COLLIDERS_PATH}/{spec['name']}")
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces).ravel()))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([MESH_COLOR]))
        # The given points are the default value; an animated mesh's time samples override it.
        points_attr = mesh.CreatePointsAttr(_vec3f(spec["points"]))
        extent_attr = mesh.CreateExtentAttr(_vec3f(spec["extent"]))
        xform_op = mesh.AddTransformOp()
        xform_op.Set(Gf.Matrix4d(1.0))
        self._prims[spec["name"]] = {"points": points_attr, "extent": extent_attr, "xform": xform_op}

    # --- frames ----------------------------------------------------------------------------------------------

    def write_frame(self, frame: int, curves: dict, xforms: dict | None = None, mesh_points: dict | None = None):
        """Write one frame at time code ``frame``.

        Every argument is checked before anything is written: a bad frame raises :class:`UsdFileError` naming the
        file, the prim and the frame, and leaves the cache as it was.

        Args:
            frame: frame number; larger than the last one written and not below ``start_frame``.
            curves: name -> (points (N, 3), velocities (N, 3) or None), world metres and metres per second, Z up,
                for every curves prim added. A prim given velocities in its first frame needs them in every frame.
            xforms: mesh name -> 4x4 world matrix, column-vector convention (``p_world = M @ [p, 1]``). A mesh left
                out of a frame has no sample there: USD interpolates between its neighbouring samples.
            mesh_points: mesh name -> (V, 3) points [m] in the mesh frame, for meshes added with animated_points.
        """
        t_start = time.perf_counter()
        prepared = self._prepare_frame(frame, curves, xforms, mesh_points)
        self.timings["check"] += time.perf_counter() - t_start
        self._author_frame(prepared)
        for name, _, v, _ in prepared["curves"]:
            if v is not None:
                self._curves[name]["velocities"] = True

    def _prepare_frame(self, frame, curves, xforms, mesh_points) -> dict:
        """Check a frame and convert it to stage units; changes nothing.

        Returns:
            ``{"frame", "curves": [(name, points, velocities or None, extent)], "xforms": {name: 4x4 stage matrix,
            column convention}, "meshes": {name: (points, extent)}}``, points float32 C-contiguous (N, 3), extents
            float32 (2, 3), or None where ``_EXTENTS_IN_CALLER`` is false (then only finiteness is checked here).
        """
        self._check_open()
        frame = int(frame)
        where = f"{self.path}: frame {frame}"
        if frame < self.start_frame:
            raise UsdFileError(f"{where}: frames start at {self.start_frame}")
        if self._frames and frame <= self._frames[-1]:
            raise UsdFileError(f"{where}: frames must increase; the last one written was {self._frames[-1]}")
        unknown = set(curves) - set(self._curves)
        if unknown:
            raise UsdFileError(f"{where}: unknown curves {sorted(unknown)}; add them with add_curves first")
        missing = set(self._curves) - set(curves)
        if missing:
            raise UsdFileError(f"{where}: no points for curves {sorted(missing)}")
        xforms = xforms or {}
        mesh_points = mesh_points or {}
        for group, given in (("xforms", xforms), ("mesh_points", mesh_points)):
            unknown = set(given) - set(self._meshes)
            if unknown:
                raise UsdFileError(f"{where}: {group} for unknown meshes {sorted(unknown)}")
        missing = {n for n, m in self._meshes.items() if m["animated"]} - set(mesh_points)
        if missing:
            raise UsdFileError(f"{where}: no mesh_points for animated meshes {sorted(missing)}")

        bounds = self._EXTENTS_IN_CALLER
        staged = []
        for name in self._curves:  # declaration order, so every frame has the same layout
            entry = self._curves[name]
            value = curves[name]
            pts, vel = value if isinstance(value, tuple | list) else (value, None)
            p, lo, hi = self._points(pts, entry["vertex_count"], f"{where}: curves {name!r} points", bounds=bounds)
            v = None
            if vel is not None:
                v = self._points(vel, entry["vertex_count"], f"{where}: curves {name!r} velocities", bounds=False)[0]
            if self._frames and (v is None) != (entry["velocities"] is None):
                state = "has" if entry["velocities"] is not None else "has no"
                raise UsdFileError(f"{where}: curves {name!r} {state} velocities in earlier frames; keep it the same")
            staged.append((name, p, v, _extent(lo, hi, entry["half_width"]) if bounds else None))
        mats = {}
        for name, m in xforms.items():
            m = np.asarray(m, dtype=np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise UsdFileError(f"{where}: xform of mesh {name!r} must be a finite 4x4 matrix")
            mats[name] = self._matrix(m)
        meshes = {}
        for name in self._meshes:
            if name not in mesh_points:
                continue
            if not self._meshes[name]["animated"]:
                raise UsdFileError(f"{where}: mesh {name!r} was not added with animated_points=True")
            p, lo, hi = self._points(mesh_points[name], self._meshes[name]["vertex_count"],
                                     f"{where}: mesh {name!r} points", bounds=bounds)
            meshes[name] = (p, _extent(lo, hi, 0.0) if bounds else None)
        return {"frame": frame, "curves": staged, "xforms": mats, "meshes": meshes}

    def _author_frame(self, prepared: dict, converted=None) -> None:
        """Set the samples of a prepared frame and save the layer (binary layers).

        Args:
            prepared: what :meth:`_prepare_frame` returned.
            converted: called once the arrays have been copied into ``Vt`` arrays (the inputs are free again).
        """
        from pxr import Gf, Usd

        t_start = time.perf_counter()
        frame = prepared["frame"]
        values = [(name, _vec3f(p), None if v is None else _vec3f(v),
                   _vec3f(_extent(*_column_bounds(p), self._prims[name]["half_width"]) if ext is None else ext))
                  for name, p, v, ext in prepared["curves"]]
        mesh_values = {name: (_vec3f(p), _vec3f(_extent(*_column_bounds(p), 0.0) if ext is None else ext))
                       for name, (p, ext) in prepared["meshes"].items()}
        t_converted = time.perf_counter()
        if converted is not None:
            converted()
        t = Usd.TimeCode(frame)
        for name, p, v, extent in values:
            prim = self._prims[name]
            prim["points"].Set(p, t)
            if v is not None:
                if prim["velocities"] is None:
                    prim["velocities"] = prim["schema"].CreateVelocitiesAttr()
                prim["velocities"].Set(v, t)
            prim["extent"].Set(extent, t)
        for name, m in prepared["xforms"].items():
            self._prims[name]["xform"].Set(Gf.Matrix4d(m.T.tolist()), t)
        for name, (p, extent) in mesh_values.items():
            self._prims[name]["points"].Set(p, t)
            self._prims[name]["extent"].Set(extent, t)
        del values, mesh_values
        self._frames.append(frame)
        t_set = time.perf_counter()
        if self._incremental:
            self._set_time_range()
            if not self._layer.Save():
                raise UsdFileError(f"{self.path}: frame {frame}: saving {self._tmp_path} failed")
        t_end = time.perf_counter()
        self.timings["convert"] += t_converted - t_start
        self.timings["set"] += t_set - t_converted
        self.timings["save"] += t_end - t_set

    @property
    def frames_written(self) -> int:
        """Number of frames written so far."""
        return len(self._frames)

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has put the file in place."""
        return self._closed

    def close(self) -> Path:
        """Set the time range to the frames written, save, and rename the file into place. Idempotent.

        Returns:
            The destination path.
        """
        if self._closed:
            return self.path
        self._set_time_range()
        if not self._layer.Save():
            raise UsdFileError(f"{self.path}: saving {self._tmp_path} failed")
        # Release the stage and layer (and the crate file's mapping) before the rename.
        self._prims.clear()
        self._stage = None
        self._layer = None
        os.replace(self._tmp_path, self.path)
        self._closed = True
        _reload_if_open(self.path)
        return self.path

    def __enter__(self) -> CacheWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False

    # --- helpers ---------------------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise UsdFileError(f"{self.path}: the cache is closed")

    def _check_name(self, name: str, where: str) -> None:
        from pxr import Sdf

        if not isinstance(name, str) or not Sdf.Path.IsValidIdentifier(name):
            raise UsdFileError(f"{where}: not a valid USD prim name (letters, digits, underscores)")
        if name in self._curves or name in self._meshes:
            raise UsdFileError(f"{where}: the name is already used")

    def _points(self, values, count: int | None, where: str, bounds: bool = True):
        """Check an (N, 3) array of finite numbers and convert it from metres, Z up, to stage units and axis.

        Returns the float32 points and their per-axis minimum and maximum (computed column by column, which is
        several times faster than a reduction over axis 0 of an (N, 3) array; a NaN or inf shows up in them), or
        None for both without ``bounds`` (then only finiteness is checked, four times faster).
        """
        a = np.asarray(values)
        if a.ndim != 2 or a.shape[1] != 3 or (count is not None and a.shape[0] != count) or a.shape[0] == 0:
            expected = f"({count}, 3)" if count is not None else "(N, 3), N > 0,"
            raise UsdFileError(f"{where}: expected an array of shape {expected} got {a.shape}")
        if self._identity:
            a = np.ascontiguousarray(a, dtype=np.float32)
        else:
            # The conversion is a signed permutation of the axes times a scale: three column copies, ~10x faster
            # than a general (N, 3) @ (3, 3) product.
            out = np.empty(a.shape, dtype=np.float32)
            for j, (i, coef) in enumerate(self._columns):
                np.multiply(a[:, i], coef, out=out[:, j], casting="unsafe")
            a = out
        if not bounds:
            if not np.isfinite(a).all():
                raise UsdFileError(f"{where}: contains NaN or infinite values")
            return a, None, None
        lo, hi = _column_bounds(a)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise UsdFileError(f"{where}: contains NaN or infinite values")
        return a, lo, hi

    def _matrix(self, m: np.ndarray) -> np.ndarray:
        """A column-convention transform of metres, Z up, expressed in stage units and axis: C M C^-1."""
        if self._identity:
            return m
        c = np.eye(4)
        c[:3, :3] = self._conv
        return c @ m @ np.linalg.inv(c)

    def _set_time_range(self) -> None:
        start = self._frames[0] if self._frames else self.start_frame
        end = self._frames[-1] if self._frames else self.start_frame
        self._stage.SetStartTimeCode(start)
        self._stage.SetEndTimeCode(end)


_LIVE_WRITERS: weakref.WeakSet = weakref.WeakSet()
"""Background writers not closed yet; their processes are stopped at interpreter exit."""

_CHILD_CODE = ("import sys; sys.path[:0] = [p for p in {paths!r} if p not in sys.path]; "
               "from hairwarp.usd import _background_main; _background_main(int(sys.argv[1]), int(sys.argv[2])); "
               "import os; sys.stderr.flush(); os._exit(0)")  # the cache is closed: skip the teardown of usd-core


def background_supported() -> bool:
    """Whether :class:`BackgroundCacheWriter` can run here: it passes file descriptors to its process (POSIX)."""
    return os.name == "posix"


def _anonymous_memory() -> int:
    """A file descriptor of an empty, nameless memory file (Linux ``memfd``, else an unlinked temporary file).

    Nothing names it, so nothing can leak: the memory goes when the last descriptor and mapping are closed, also
    when a process is killed.
    """
    if hasattr(os, "memfd_create"):
        return os.memfd_create("hairwarp-cache-frames", os.MFD_CLOEXEC)
    with tempfile.TemporaryFile(prefix="hairwarp-cache-frames-") as f:
        return os.dup(f.fileno())


def _error_text(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, UsdFileError) else f"{type(exc).__name__}: {exc}"


@atexit.register
def _stop_background_writers() -> None:
    """Stop the processes of writers never closed (their temporary files keep the frames saved, as inline)."""
    for writer in list(_LIVE_WRITERS):
        writer._abandon()


class BackgroundCacheWriter(CacheWriter):
    """A :class:`CacheWriter` whose ``Vt`` conversion, authoring and crate saves run in a second process.

    The interface, the file and the guarantees are those of :class:`CacheWriter`. :meth:`write_frame` checks the
    frame in the caller (a bad frame raises there at once, naming the file, the prim and the frame, and is not
    sent), copies its arrays into a ring of ``slots`` frame buffers in shared memory, hands the slot to the writer
    process and returns; when every slot is taken it waits for the oldest to be converted (back-pressure). The
    writer process owns the USD stage: it converts, authors, and saves every frame of a binary layer, so a crash
    of either process leaves the frames saved so far in the temporary file. A failure in the writer process
    (e.g. the folder removed) is raised by the next :meth:`write_frame` or by :meth:`close`, naming the file.
    :meth:`close` waits for the frames in flight, saves, renames the file into place and ends the process.

    The process is started with the interpreter's executable (``multiprocessing``'s, see
    ``multiprocessing.set_executable``) and imports only hairwarp.usd and usd-core: no fork of a process that runs
    Warp, and a script that creates a writer needs no ``if __name__ == "__main__"`` guard. It ignores SIGINT, so
    Ctrl-C in a run reaches only the caller, whose ``with`` block then closes the cache. POSIX only
    (:func:`background_supported`).

    Args:
        path, fps, start_frame, meters_per_unit, up_axis, comment: as :class:`CacheWriter`.
        slots: frame buffers in shared memory (each the size of one frame's points and velocities); two let the
            caller fill one while the writer converts the other.

    Attributes:
        timings: seconds per phase, summed over the frames: in the caller ``check`` (validation, extents),
            ``copy`` (into shared memory), ``wait`` (for a free slot); in the writer process ``convert`` (extents
            and ``Vt`` arrays), ``set``, ``save`` (complete once the cache is closed).
        frames_saved: frames the writer process has saved so far.
    """

    _EXTENTS_IN_CALLER = False  # the caller checks finiteness (4x cheaper); the writer process takes the extents

    def __init__(self, path, *, fps: float, start_frame: int = 0, meters_per_unit: float = 1.0, up_axis: str = "Z",
                 comment: str = "", slots: int = 2):
        self._setup(path, fps, start_frame, meters_per_unit, up_axis)
        if not background_supported():
            raise UsdFileError(f"{self.path}: the background writer needs a POSIX system; use CacheWriter")
        if int(slots) < 1:
            raise UsdFileError(f"{self.path}: slots must be at least 1, not {slots!r}")
        self.timings = {"check": 0.0, "copy": 0.0, "wait": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0}
        self.frames_saved = 0
        self._slot_count = int(slots)
        self._free: list[int] = []
        self._layout: dict | None = None
        self._ring = None
        self._views: list[dict] = []
        self._failure: str | None = None
        self._failure_raised = False
        self._proc = None
        self._conn = None
        self._ring_fd = -1
        self._tmp_path = None
        self._start(comment)

    # --- the process -----------------------------------------------------------------------------------------

    def _start(self, comment: str) -> None:
        import multiprocessing.connection
        import multiprocessing.spawn
        import socket
        import subprocess

        self.path.parent.mkdir(parents=True, exist_ok=True)  # as the inline writer: raised here, at once
        if not os.access(self.path.parent, os.W_OK | os.X_OK):
            raise UsdFileError(f"{self.path}: its folder is not writable")
        ours, theirs = socket.socketpair()
        try:
            self._ring_fd = _anonymous_memory()
            paths = [p for p in sys.path if isinstance(p, str)]
            self._proc = subprocess.Popen(
                [multiprocessing.spawn.get_executable(), "-c", _CHILD_CODE.format(paths=paths),
                 str(theirs.fileno()), str(self._ring_fd)],
                pass_fds=(theirs.fileno(), self._ring_fd), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            self._release_resources()
            raise
        finally:
            theirs.close()
        self._conn = multiprocessing.connection.Connection(ours.detach())
        _LIVE_WRITERS.add(self)
        # Not waited for: the process loads usd-core (about half a second) while the caller goes on.
        self._post(("open", {"path": str(self.path), "fps": self.fps, "start_frame": self.start_frame,
                             "meters_per_unit": self.meters_per_unit, "up_axis": self.up_axis, "comment": comment}))

    def _died(self) -> UsdFileError:
        code = self._proc.poll() if self._proc is not None else None
        keeps = f"; {self._tmp_path} keeps the frames saved before it" if self._tmp_path else ""
        return UsdFileError(f"{self.path}: the background writer process ended unexpectedly (exit code {code})"
                            f" after saving {self.frames_saved} frames{keeps}")

    def _receive(self):
        """The next message of the writer process, waiting for it; raises if the process is gone."""
        while True:
            try:
                if self._conn.poll(0.5):
                    return self._conn.recv()
            except (EOFError, OSError):
                raise self._died() from None
            if self._proc.poll() is not None and not self._conn.poll(0):
                raise self._died()

    def _handle(self, message) -> tuple | None:
        """Book an asynchronous message (a slot released, a frame saved, a frame failed); return a reply."""
        kind = message[0]
        if kind == "released":
            self._free.append(message[1])
        elif kind == "saved":
            self.frames_saved += 1
            for key, seconds in message[2].items():
                self.timings[key] += seconds
        elif kind == "opened":
            self._tmp_path = Path(message[1])
        elif kind == "failed":
            if self._failure is None:
                self._failure = f"{self.path}: the background writer failed at {message[1]}: {message[2]}"
        else:
            return message
        return None

    def _drain(self) -> None:
        """Book every message already arrived, without waiting."""
        try:
            while self._conn.poll(0):
                reply = self._handle(self._conn.recv())
                if reply is not None:
                    raise UsdFileError(f"{self.path}: unexpected reply of the background writer: {reply!r}")
        except (EOFError, OSError):
            raise self._died() from None

    def _post(self, message) -> None:
        """Send a request that has no reply (a failure comes back as a ``failed`` message)."""
        try:
            self._conn.send(message)
        except OSError:
            raise self._died() from None

    def _request(self, message):
        """Send a request and wait for its reply, booking the asynchronous messages that come first."""
        try:
            self._conn.send(message)
        except OSError:
            raise self._died() from None
        while True:
            reply = self._handle(self._receive())
            if reply is None:
                continue
            if reply[0] == "error":
                raise UsdFileError(reply[1])
            return reply[1]

    def _raise_failure(self) -> None:
        if self._failure is not None:
            self._failure_raised = True
            raise UsdFileError(self._failure)

    # --- setup and frames ------------------------------------------------------------------------------------

    def _author_curves(self, spec: dict) -> None:
        self._drain()
        self._raise_failure()
        self._post(("add_curves", spec))

    def _author_mesh(self, spec: dict) -> None:
        self._drain()
        self._raise_failure()
        self._post(("add_mesh", spec))

    def write_frame(self, frame: int, curves: dict, xforms: dict | None = None, mesh_points: dict | None = None):
        """Check the frame here, queue it for the writer process, return (see :meth:`CacheWriter.write_frame`).

        Raises:
            UsdFileError: a bad frame (nothing is queued), or an earlier frame that failed in the writer process.
        """
        self._check_open()
        self._drain()
        self._raise_failure()
        super().write_frame(frame, curves, xforms, mesh_points)

    def _author_frame(self, prepared: dict, converted=None) -> None:
        t_start = time.perf_counter()
        if self._layout is None:
            self._make_ring(prepared)
        while not self._free:
            self._handle(self._receive())
            self._raise_failure()
        slot = self._free.pop()
        t_slot = time.perf_counter()
        views = self._views[slot]
        curves = []
        for name, p, v, extent in prepared["curves"]:
            np.copyto(views[(name, "points")], p)
            if v is not None:
                np.copyto(views[(name, "velocities")], v)
            curves.append((name, v is not None, extent))
        meshes = {}
        for name, (p, extent) in prepared["meshes"].items():
            np.copyto(views[(name, "mesh")], p)
            meshes[name] = extent
        t_copied = time.perf_counter()
        try:
            self._conn.send(("frame", slot, prepared["frame"], curves, prepared["xforms"], meshes))
        except OSError:
            raise self._died() from None
        self._frames.append(prepared["frame"])
        self.timings["wait"] += t_slot - t_start
        self.timings["copy"] += t_copied - t_slot

    def _make_ring(self, prepared: dict) -> None:
        """Size the slots on the first frame (later frames have the same arrays) and share them with the process."""
        import mmap

        layout, size = {}, 0
        arrays = []
        for name, p, v, _ in prepared["curves"]:
            arrays.append(((name, "points"), p))
            if v is not None:
                arrays.append(((name, "velocities"), v))
        arrays += [((name, "mesh"), p) for name, (p, _) in prepared["meshes"].items()]
        for key, a in arrays:
            layout[key] = (size, len(a))
            size += -(-a.nbytes // 64) * 64  # 64-byte aligned
        slot_bytes = max(-(-size // mmap.PAGESIZE) * mmap.PAGESIZE, mmap.PAGESIZE)
        os.ftruncate(self._ring_fd, slot_bytes * self._slot_count)
        self._ring = mmap.mmap(self._ring_fd, slot_bytes * self._slot_count)
        self._views = [{key: np.frombuffer(self._ring, np.float32, 3 * n, s * slot_bytes + off).reshape(n, 3)
                        for key, (off, n) in layout.items()} for s in range(self._slot_count)]
        self._layout = layout
        self._post(("ring", slot_bytes, self._slot_count, layout))
        self._free = list(range(self._slot_count))[::-1]

    def flush(self) -> None:
        """Wait until the writer process has saved every frame given so far.

        Raises:
            UsdFileError: a frame failed in the writer process.
        """
        self._check_open()
        while self.frames_saved < len(self._frames) and self._failure is None:
            self._handle(self._receive())
        self._raise_failure()

    # --- closing ---------------------------------------------------------------------------------------------

    def close(self) -> Path:
        """Wait for the frames in flight, save, rename the file into place and end the writer process. Idempotent.

        Raises:
            UsdFileError: the writer process failed (at a frame, or saving); the message names the file and says
                what it keeps. A failure already raised by :meth:`write_frame` is not raised again.
        """
        if self._closed:
            return self.path
        error = None
        try:
            self._request(("close",))
        except UsdFileError as exc:
            error = exc
        finally:
            self._closed = True
            self._shutdown()
        if self._failure is not None and not self._failure_raised:
            self._failure_raised = True
            raise UsdFileError(self._failure + (f"; and at close: {error}" if error else ""))
        if error is not None and self._failure is None:
            raise error
        _reload_if_open(self.path)
        return self.path

    def _shutdown(self, timeout: float = 30.0) -> None:
        """End the process (it exits after ``close`` or when its pipe closes) and free the pipe and the ring."""
        import subprocess

        _LIVE_WRITERS.discard(self)
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._release_resources()

    def _release_resources(self) -> None:
        self._views = []
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        if self._ring_fd >= 0:
            os.close(self._ring_fd)
            self._ring_fd = -1

    def _abandon(self) -> None:
        """Stop the process without closing the cache (the temporary file keeps the frames saved so far)."""
        if not self._closed:
            self._closed = True
            self._shutdown(timeout=10.0)

    def __del__(self):
        try:
            self._abandon()
        except Exception:  # interpreter shutdown: the atexit hook or the closed pipe ends the process
            pass


def _background_main(conn_fd: int, ring_fd: int) -> None:
    """The writer process of :class:`BackgroundCacheWriter`: serves its requests until ``close`` or a closed pipe.

    Requests: ``("open", kwargs)`` (answered ``("opened", temporary path)``), ``("add_curves", spec)``,
    ``("add_mesh", spec)``, ``("ring", slot_bytes, slots, layout)``, ``("frame", slot, frame, curves, xforms,
    meshes)``, ``("close",)`` (answered ``("ok", path)`` or ``("error", message)``). A frame sends ``("released",
    slot)`` once its arrays are copied into ``Vt`` arrays, then ``("saved", frame, timings)``. A request that fails
    sends ``("failed", what, message)``; the later requests are then skipped (frames released unwritten), and
    ``close`` still saves what the stage holds.
    """
    import mmap
    import multiprocessing.connection
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _keep_freed_memory()
    conn = multiprocessing.connection.Connection(conn_fd)
    writer, ring, failed = None, None, False
    views: list[dict] = []
    try:
        while True:
            try:
                message = conn.recv()
            except EOFError:  # the caller is gone: leave the temporary file with the frames saved so far
                break
            kind = message[0]
            if kind == "frame":
                _, slot, frame, curves, xforms, meshes = message
                released = []

                def release(slot=slot, released=released):
                    if not released:
                        released.append(True)
                        conn.send(("released", slot))

                if failed:
                    release()
                    continue
                try:
                    before = dict(writer.timings)
                    v = views[slot]
                    prepared = {"frame": frame, "xforms": xforms,
                                "curves": [(name, v[(name, "points")], v[(name, "velocities")] if has_v else None,
                                            extent) for name, has_v, extent in curves],
                                "meshes": {name: (v[(name, "mesh")], extent) for name, extent in meshes.items()}}
                    writer._author_frame(prepared, converted=release)
                    del prepared
                    conn.send(("saved", frame, {k: writer.timings[k] - before[k] for k in before if k != "check"}))
                except Exception as exc:  # reported to the caller, which raises it naming the file
                    failed = True
                    release()
                    conn.send(("failed", f"frame {frame}", _error_text(exc)))
                continue
            if kind == "close":
                try:
                    conn.send(("ok", str(writer.close()) if writer is not None else None))
                except Exception as exc:
                    conn.send(("error", _error_text(exc)))
                break
            if failed:
                continue
            try:
                if kind == "open":
                    writer = CacheWriter(**message[1])
                    conn.send(("opened", str(writer._tmp_path)))
                elif kind == "add_curves":
                    writer._author_curves(message[1])
                elif kind == "add_mesh":
                    writer._author_mesh(message[1])
                elif kind == "ring":
                    _, slot_bytes, slots, layout = message
                    ring = mmap.mmap(ring_fd, slot_bytes * slots)
                    views = [{key: np.frombuffer(ring, np.float32, 3 * n, s * slot_bytes + off).reshape(n, 3)
                              for key, (off, n) in layout.items()} for s in range(slots)]
                else:
                    raise ValueError(f"unknown request {kind!r}")
            except Exception as exc:
                failed = True
                what = {"open": "opening the file", "add_curves": "adding curves", "add_mesh": "adding a mesh",
                        "ring": "mapping the shared frames"}.get(kind, kind)
                conn.send(("failed", what, _error_text(exc)))
    finally:
        views = []
        if ring is not None:
            try:
                ring.close()
            except BufferError:  # a view still referenced by a traceback; the process ends anyway
                pass
        conn.close()


def _keep_freed_memory() -> None:
    """In the writer process: keep freed large blocks in the heap (glibc), so the ``Vt`` array of the next frame
    reuses pages already mapped instead of faulting fresh ones in (10x cheaper allocation for 100 MB arrays)."""
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    mallopt(m_mmap_threshold, 1 << 30)
    mallopt(m_trim_threshold, (1 << 31) - 1)


# --- static grooms ---------------------------------------------------------------------------------------------


def write_curves(path, polylines, *, widths=None, up_axis: str = "Z", meters_per_unit: float = 1.0) -> Path:
    """Write a static groom: one linear BasisCurves prim ``/World/Hair/groom`` with the given polylines.

    Args:
        path: destination, .usd, .usda or .usdc (written to a temporary file and renamed into place).
        polylines: list of (n_i, 3) arrays [m], root first, Z up; n_i >= 2.
        widths: diameter [m]: None (a default taper), a number, a (root, tip) pair, or one value per vertex.
        up_axis: "Z" or "Y" for the stage; points are rotated into it.
        meters_per_unit: stage unit, in metres.

    Returns:
        The destination path.
    """
    path = Path(path).absolute()
    _check_suffix(path)
    _check_stage_units(path, up_axis, meters_per_unit)
    if len(polylines) == 0:
        raise UsdFileError(f"{path}: no polylines to write")
    arrays = []
    for i, line in enumerate(polylines):
        a = np.asarray(line, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 2 or not np.all(np.isfinite(a)):
            raise UsdFileError(f"{path}: strand {i} must be a finite (n, 3) array with n >= 2, got {a.shape}")
        arrays.append(a)
    counts = np.array([len(a) for a in arrays], dtype=np.int64)
    points = _apply_linear(np.concatenate(arrays), _conversion(up_axis, meters_per_unit).T)
    w, interp = _vertex_widths(counts, widths, str(path))
    w = w / meters_per_unit

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".partial{path.suffix}", dir=path.parent)
    os.close(fd)
    _default_permissions(tmp)
    try:
        layer, stage = _new_stage(tmp, up_axis=up_axis, meters_per_unit=meters_per_unit,
                                  doc="hairwarp groom: hair curves under /World/Hair, root first.")
        curves = _define_curves(stage, f"{HAIR_PATH}/groom", counts, w, interp, basis="linear", kind="dense",
                                purpose="default")
        curves.CreatePointsAttr(_vec3f(points))
        h = 0.5 * float(w.max())
        curves.CreateExtentAttr(_vec3f(np.stack([points.min(axis=0) - h, points.max(axis=0) + h])))
        if not layer.Save():
            raise UsdFileError(f"{path}: saving {tmp} failed")
        del stage, layer, curves
        os.replace(tmp, path)
        _reload_if_open(path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


# --- reading ---------------------------------------------------------------------------------------------------


def _open_stage(path):
    """Open a stage read-only, raising UsdFileError naming the file when it is missing or unreadable."""
    from pxr import Tf, Usd

    path = Path(path)
    if not path.is_file():
        raise UsdFileError(f"{path}: no such file")
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as e:
        raise UsdFileError(f"{path}: cannot be opened as USD ({str(e).strip().splitlines()[-1]})") from e
    if stage is None:
        raise UsdFileError(f"{path}: cannot be opened as USD")
    return stage


def _stage_to_metres_z(stage) -> np.ndarray:
    """3x3 matrix taking this stage's units and up axis to metres, Z up."""
    from pxr import UsdGeom

    up = UsdGeom.GetStageUpAxis(stage)
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    return np.linalg.inv(_conversion("Y" if up == UsdGeom.Tokens.y else "Z", mpu))


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


def read_curves(path) -> list[np.ndarray]:
    """Every curve of every BasisCurves prim in a stage, as world polylines in metres, Z up.

    Points are read at the default time, or at the first time sample when they are animated; world transforms
    are applied, then ``metersPerUnit`` and ``upAxis`` are converted (a Y-up point (x, y, z) becomes (x, -z, y)).
    Cubic curves return their control points.

    Args:
        path: a .usd, .usda or .usdc file.

    Returns:
        A list of (n_i, 3) float64 arrays, root first, in stage traversal order.

    Raises:
        UsdFileError: the file is missing, unreadable, or has no BasisCurves prim.
    """
    from pxr import UsdGeom

    stage = _open_stage(path)
    conv = _stage_to_metres_z(stage)
    out = []
    found = False
    for prim in _prims(stage, UsdGeom.BasisCurves):
        found = True
        time = _first_time(UsdGeom.BasisCurves(prim).GetPointsAttr())
        pts, counts = _curve_arrays(prim, time, UsdGeom.XformCache(time), conv, path)
        out.extend(np.split(pts, np.cumsum(counts)[:-1]))
    if not found:
        raise UsdFileError(f"{path}: no BasisCurves prim in the stage")
    return out


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


def read_frames(path, frames=None) -> list[dict]:
    """Curves and meshes of a cache, frame by frame, in world metres, Z up (for previews).

    Args:
        path: a cache written by :class:`CacheWriter` (any stage with BasisCurves works).
        frames: frame numbers (time codes) to read; None reads every time sample of curve points, mesh points and
            transforms (or the default time when nothing is animated).

    Returns:
        One dict per frame: ``{"frame": float, "time": seconds, "curves": {prim name: (points (N, 3) float64,
        curve_vertex_counts (C,) int64)}, "meshes": {prim name: (vertices (V, 3) in world space, triangles (F, 3),
        world matrix 4x4 in the column convention)}}``.
    """
    from pxr import UsdGeom

    stage = _open_stage(path)
    conv = _stage_to_metres_z(stage)
    curve_prims = list(_prims(stage, UsdGeom.BasisCurves))
    mesh_prims = list(_prims(stage, UsdGeom.Mesh))
    if not curve_prims:
        raise UsdFileError(f"{path}: no BasisCurves prim in the stage")
    if frames is None:
        frames = _time_samples(stage) or [stage.GetStartTimeCode()]
    tcps = stage.GetTimeCodesPerSecond() or 24.0
    curve_names = _unique_names(curve_prims)
    mesh_names = _unique_names(mesh_prims)
    out = []
    for f in frames:
        xc = UsdGeom.XformCache(float(f))
        curves = {n: _curve_arrays(p, float(f), xc, conv, path) for n, p in zip(curve_names, curve_prims, strict=True)}
        meshes = {n: _mesh_arrays(p, float(f), xc, conv) for n, p in zip(mesh_names, mesh_prims, strict=True)}
        out.append({"frame": float(f), "time": float(f) / tcps, "curves": curves, "meshes": meshes})
    return out


# --- animated colliders ----------------------------------------------------------------------------------------

# A world transform's scale, shear or mirror (the symmetric factor of its polar decomposition) is baked into the
# vertices when it stays within this (relative, float64 matrices of float32 or float64 authored ops) of its value
# at the first time sample; colliders move rigidly.
_CONSTANT_SCALE_RTOL = 1.0e-6


def _find_mesh(stage, prim_path, path):
    from pxr import UsdGeom

    if prim_path is None:
        prim = next(_prims(stage, UsdGeom.Mesh), None)
        if prim is None:
            raise UsdFileError(f"{path}: no Mesh prim in the stage")
        return prim
    prim = stage.GetPrimAtPath(str(prim_path))
    if not prim or not prim.IsValid():
        raise UsdFileError(f"{path}: no prim at {prim_path}")
    if not prim.IsA(UsdGeom.Mesh):
        raise UsdFileError(f"{path}: {prim_path} is a {prim.GetTypeName() or 'typeless prim'}, not a Mesh")
    return prim


def _transform_times(prim) -> set[float]:
    """Time codes of the transform samples of a prim and of every ancestor (its world matrix depends on them)."""
    from pxr import UsdGeom

    times: set[float] = set()
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable:
            times.update(xformable.GetTimeSamples())
        prim = prim.GetParent()
    return times


def _rigid_factor(linear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``linear = R K`` with R a rotation and K symmetric (the polar decomposition; a mirror goes into K)."""
    u, sv, vt = np.linalg.svd(linear)
    d = np.ones(3)
    if np.linalg.det(u @ vt) < 0.0:
        d[2] = -1.0
    rot = u @ np.diag(d) @ vt
    return rot, rot.T @ linear


def read_animated_mesh(path, prim_path=None):
    """A Mesh prim and its animation, in metres, Z up: for colliders that follow a USD animation.

    The world transform of the prim (its own transform ops and its ancestors') is read at every time code where
    any of them, or the prim's points, has a sample; ``metersPerUnit`` and ``upAxis`` are converted as by the
    other readers. A scale, shear or mirror that is the same at every sample is baked into the vertices (the
    winding is reversed with a mirror) so that the returned matrices are rigid; polygons are split into fans and
    a ``leftHanded`` orientation is turned into right-handed winding, so the faces point outward as authored.

    Args:
        path: a .usd, .usda, .usdc or .usdz file.
        prim_path: the Mesh prim; None takes the first Mesh in traversal order.

    Returns:
        ``(vertices, faces, times, matrices)``: vertices [m] in the mesh's own frame, float64 ``(V, 3)``, or
        ``(T, V, 3)`` when the points themselves are time-sampled (then one set per time); faces ``(F, 3)`` int64;
        times [s] ``(T,)`` (time code / timeCodesPerSecond; a stage with no sample gives one time, 0, read at
        the default time); matrices ``(T, 4, 4)`` rigid world poses, column convention (``p_world = M @ [p, 1]``).
        ``vertices`` moved by ``matrices[i]`` is the mesh in the world at ``times[i]``.

    Raises:
        UsdFileError: missing or unreadable file, no Mesh prim (or ``prim_path`` is not one), a scale that changes
            with time, or a point count that changes with time.
    """
    return _read_animated_mesh(path, prim_path)[:4]


def _read_animated_mesh(path, prim_path):
    """:func:`read_animated_mesh`, and the prim's name."""
    from pxr import Usd, UsdGeom

    stage = _open_stage(path)
    prim = _find_mesh(stage, prim_path, path)
    where = f"{path}: {prim.GetPath()}"
    mesh = UsdGeom.Mesh(prim)
    conv = _stage_to_metres_z(stage)
    c4 = np.eye(4)
    c4[:3, :3] = conv
    c4_inv = np.linalg.inv(c4)
    points_attr = mesh.GetPointsAttr()
    point_times = points_attr.GetTimeSamples()
    codes = sorted(_transform_times(prim) | set(point_times))
    tcps = stage.GetTimeCodesPerSecond() or 24.0
    time_codes = [Usd.TimeCode(t) for t in codes] or [Usd.TimeCode.Default()]
    times = np.array(codes, dtype=np.float64) / tcps if codes else np.zeros(1)

    matrices = np.empty((len(time_codes), 4, 4))
    scale = None
    for i, tc in enumerate(time_codes):
        m_usd = np.array(UsdGeom.XformCache(tc).GetLocalToWorldTransform(prim), dtype=np.float64)
        # Row-vector USD matrix in stage units -> column convention in metres, Z up, acting on metre Z-up points.
        world = c4 @ m_usd.T @ c4_inv
        rot, k = _rigid_factor(world[:3, :3])
        if scale is None:
            scale = k
        elif np.abs(k - scale).max() > _CONSTANT_SCALE_RTOL * max(np.abs(scale).max(), 1e-300):
            raise UsdFileError(f"{where}: its world scale changes with time (at time code {codes[i]:g}); "
                               "colliders move rigidly, so only a constant scale can be baked into the mesh")
        matrices[i] = np.eye(4)
        matrices[i, :3, :3] = rot
        matrices[i, :3, 3] = world[:3, 3]

    first = time_codes[0]
    faces = _triangles(mesh, first)
    if (mesh.GetOrientationAttr().Get(first) == UsdGeom.Tokens.leftHanded) != (np.linalg.det(scale) < 0.0):
        faces = faces[:, ::-1].copy()

    def local_points(tc):
        pts = np.asarray(points_attr.Get(tc) or [], dtype=np.float64).reshape(-1, 3)
        # Metres Z up in the mesh frame, with the constant scale applied: (K C p) as rows.
        return pts @ (scale @ conv).T

    if point_times:
        frames = [local_points(tc) for tc in time_codes]
        counts = {len(f) for f in frames}
        if len(counts) != 1:
            raise UsdFileError(f"{where}: the number of points changes with time ({sorted(counts)})")
        vertices = np.stack(frames)
    else:
        vertices = local_points(first)
    if vertices.size == 0 or faces.size == 0:
        raise UsdFileError(f"{where}: the mesh has no points or no faces")
    if faces.min() < 0 or faces.max() >= vertices.shape[-2]:
        raise UsdFileError(f"{where}: face vertex indices out of range for {vertices.shape[-2]} points")
    return vertices, faces, times, matrices, prim.GetName()


def mesh_motion(times, matrices):
    """A rigid motion through sampled world poses, e.g. those of :func:`read_animated_mesh`.

    The poses become the keys of a :class:`hairwarp.motion.Keyframes` (about the world origin): translation by
    cubic Hermite with Catmull-Rom tangents, rotation by a cubic Hermite in the tangent space of SO(3), so
    position and velocity are continuous and ``evaluate(t)`` gives analytic world velocities and accelerations.
    The pose is held before the first and after the last sample, so the velocity is zero there. Usable as a
    world collider's ``motion`` (``Collider(..., attach="world", motion=mesh_motion(times, matrices))``) or as a
    head motion.

    Args:
        times: strictly increasing sample times [s], (T,).
        matrices: rigid world poses, (T, 4, 4), column convention; consecutive ones under 180 degrees apart.

    Returns:
        The :class:`hairwarp.motion.Keyframes`; its ``evaluate(t)`` returns a ``MotionSample`` with ``matrix()``,
        ``linear_velocity`` (of the frame origin), ``angular_velocity``, ``linear_acceleration`` and
        ``angular_acceleration``, world.
    """
    from hairwarp.colliders import matrix_to_transform
    from hairwarp.motion import Keyframes

    m = np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4)
    xf = np.array([matrix_to_transform(x) for x in m]).reshape(-1, 7)
    return Keyframes(np.asarray(times, dtype=np.float64).reshape(-1), xf[:, :3], xf[:, 3:])


def read_animated_collider(path, prim_path=None, *, name: str | None = None, **options):
    """A world collider that follows a Mesh prim's animation in a USD file (rigid; see :func:`read_animated_mesh`).

    Args:
        path: the USD file.
        prim_path: the Mesh prim; None takes the first one.
        name: collider name; the prim's name by default.
        **options: ``thickness``, ``friction`` of :class:`hairwarp.colliders.Collider`.

    Returns:
        A MESH :class:`hairwarp.colliders.Collider` with ``attach="world"`` and ``motion`` from :func:`mesh_motion`
        (static when the stage has a single sample).

    Raises:
        UsdFileError: as :func:`read_animated_mesh`, and for time-sampled points (a deforming mesh cannot be a
            rigid collider).
    """
    import trimesh

    from hairwarp.colliders import Collider

    vertices, faces, times, matrices, prim_name = _read_animated_mesh(path, prim_path)
    if vertices.ndim == 3:
        raise UsdFileError(f"{path}: mesh {prim_name!r} deforms (time-sampled points); a collider must be rigid")
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    motion = mesh_motion(times, matrices) if len(times) > 1 else None
    local = np.eye(4) if motion is not None else matrices[0]
    return Collider.from_trimesh(mesh, local_xform=local, name=name or prim_name, attach="world", motion=motion,
                                 **options)


def _unique_names(prims) -> list[str]:
    names = [p.GetName() for p in prims]
    if len(set(names)) == len(names):
        return names
    return [str(p.GetPath()) for p in prims]


def describe(path) -> str:
    """A human summary of a USD cache or groom, for ``hairwarp info``.

    Lists the stage metadata (up axis, metres per unit, fps, frame range), each curves prim (curve count,
    vertices, basis, time samples, velocities, widths), each mesh (points, faces, animated or not), the world
    extent in metres (Z up) of the first and last frame, the file size and the bytes per frame.
    """
    from pxr import Usd, UsdGeom

    path = Path(path)
    stage = _open_stage(path)
    conv = _stage_to_metres_z(stage)
    size = path.stat().st_size
    layer = stage.GetRootLayer()
    up = UsdGeom.GetStageUpAxis(stage)
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    fps = stage.GetTimeCodesPerSecond()
    times = _time_samples(stage)
    lines = [f"{path}  ({_human_bytes(size)}, {layer.GetFileFormat().formatId})"]
    lines.append(f"  up axis {up}, {mpu:g} m per unit, {fps:g} time codes per second, default prim "
                 f"{stage.GetDefaultPrim().GetPath() if stage.GetDefaultPrim() else 'none'}")
    if times:
        lines.append(f"  frames {times[0]:g} .. {times[-1]:g}: {len(times)} time samples "
                     f"({(times[-1] - times[0]) / fps:.3f} s)")
    else:
        lines.append("  static: no time samples")
    doc = layer.documentation.strip()
    if doc:
        lines.append("  doc: " + doc.replace("\n", " / "))
    for prim in _prims(stage, UsdGeom.BasisCurves):
        c = UsdGeom.BasisCurves(prim)
        counts = np.asarray(c.GetCurveVertexCountsAttr().Get() or [], dtype=np.int64)
        ctype = c.GetTypeAttr().Get()
        basis = "linear"
        if ctype != UsdGeom.Tokens.linear:
            basis = f"cubic {c.GetBasisAttr().Get()} ({c.GetWrapAttr().Get()})"
        n_samples = c.GetPointsAttr().GetNumTimeSamples()
        widths = np.asarray(c.GetWidthsAttr().Get() or [], dtype=np.float64) * mpu
        wtxt = f"widths {widths.max():.3g}..{widths.min():.3g} m" if widths.size else "no widths"
        kind = prim.GetAttribute("hairwarp:curveKind").Get() if prim.HasAttribute("hairwarp:curveKind") else None
        vel = "velocities" if c.GetVelocitiesAttr().HasAuthoredValue() else "no velocities"
        lines.append(f"  curves {prim.GetPath()}{f' [{kind}]' if kind else ''}: {len(counts)} curves, "
                     f"{int(counts.sum())} vertices ({_count_range(counts)} per curve), {basis}, "
                     f"{n_samples} time samples, {vel}, {wtxt}, purpose {c.GetPurposeAttr().Get()}")
    for prim in _prims(stage, UsdGeom.Mesh):
        m = UsdGeom.Mesh(prim)
        n_pts = len(m.GetPointsAttr().Get(_first_time(m.GetPointsAttr())) or [])
        n_faces = len(m.GetFaceVertexCountsAttr().Get() or [])
        pts_anim = m.GetPointsAttr().GetNumTimeSamples()
        xf_anim = max([op.GetAttr().GetNumTimeSamples() for op in m.GetOrderedXformOps()] or [0])
        pts_txt = f"animated ({pts_anim} samples)" if pts_anim else "static"
        xf_txt = f"animated ({xf_anim} samples)" if xf_anim else "static"
        lines.append(f"  mesh {prim.GetPath()}: {n_pts} points, {n_faces} faces, points {pts_txt}, transform {xf_txt}")
    purposes = [UsdGeom.Tokens.default_, UsdGeom.Tokens.render, UsdGeom.Tokens.proxy, UsdGeom.Tokens.guide]
    for label, t in (("first", times[0] if times else None), ("last", times[-1] if times else None)):
        if label == "last" and len(times) < 2:
            break
        time = Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)
        box = UsdGeom.BBoxCache(time, purposes, useExtentsHint=False).ComputeWorldBound(stage.GetPseudoRoot())
        rng = box.ComputeAlignedRange()
        if rng.IsEmpty():
            continue
        corners = np.array([[x, y, z] for x in (rng.GetMin()[0], rng.GetMax()[0]) for y in (rng.GetMin()[1],
                            rng.GetMax()[1]) for z in (rng.GetMin()[2], rng.GetMax()[2])]) @ conv.T
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        when = "static" if t is None else f"{label} frame {t:g}"
        lines.append(f"  extent ({when}), m, Z up: min {_fmt3(lo)} max {_fmt3(hi)} size {_fmt3(hi - lo)}")
    if times:
        lines.append(f"  {_human_bytes(size / len(times))} per frame")
    return "\n".join(lines)


def _count_range(counts: np.ndarray) -> str:
    if counts.size == 0:
        return "0"
    lo, hi = int(counts.min()), int(counts.max())
    return str(lo) if lo == hi else f"{lo}..{hi}"


def _fmt3(v) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024.0 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} GiB"


def bench_usd_write(counts=(10_000, 100_000), quick: bool = False, device=None, *, points_per_curve: int = 81,
                    frames: int | None = None) -> dict:
    """Time :meth:`CacheWriter.write_frame` of dense curves with velocities into a temporary ``.usdc``, per phase.

    The curves are synthetic random walks (a fresh array per frame, so the crate cannot share them between
    frames); :func:`hairwarp.benchmarks.dense.bench_dense_frame` times the same writes with simulated hair.

    Args:
        counts: curve counts.
        quick: two frames per count instead of four.
        device: not used (writing is host work); accepted so every stage hook is called alike.
        points_per_curve: vertices per curve (81: 20 segments Hermite-sampled 4 times).
        frames: timed frames per count (after one untimed frame).

    Returns:
        ``{"points_per_curve", "frames", "results": [{"count", "points", "write_s", "check_s", "convert_s", "set_s",
        "save_s", "bytes_per_frame", "megabytes_per_s"}, ...]}``, seconds per frame (mean over the timed frames).
    """
    frames = int(frames or (2 if quick else 4))
    rng = np.random.default_rng(0)
    results = []
    with tempfile.TemporaryDirectory(prefix="hairwarp-bench-usd-") as tmp:
        for n in counts:
            npts = int(n) * int(points_per_curve)
            base = np.cumsum(rng.normal(scale=1e-3, size=(npts, 3)).astype(np.float32), axis=0)
            path = Path(tmp) / f"bench{n}.usdc"
            wall = 0.0
            with CacheWriter(path, fps=30.0) as cache:
                cache.add_curves("hair", np.full(int(n), int(points_per_curve)))
                for f in range(frames + 1):
                    points, velocities = base + np.float32(1e-4 * f), base * np.float32(0.01 * (f + 1))
                    if f == 1:
                        before = dict(cache.timings)
                    t0 = time.perf_counter()
                    cache.write_frame(f, {"hair": (points, velocities)})
                    wall += (time.perf_counter() - t0) if f > 0 else 0.0
            size = path.stat().st_size
            per_frame = wall / frames
            results.append({"count": int(n), "points": npts, "write_s": per_frame,
                            **{f"{k}_s": (cache.timings[k] - before[k]) / frames for k in before},
                            "bytes_per_frame": size / (frames + 1),
                            "megabytes_per_s": 24.0 * npts / per_frame / 1e6})
    return {"points_per_curve": int(points_per_curve), "frames": frames, "results": results}
