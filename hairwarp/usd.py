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
the time goes to building the ``Vt`` arrays that USD stores (a copy made element by element inside usd-core, about
1 GB/s: 55 % of a frame), to the crate's write in ``Sdf.Layer.Save`` (about 2 GB/s: 27 %) and to the extent and
finiteness checks (13 %), measured for 100,000 dense strands on two CPU cores by ``hairwarp.benchmarks.dense``;
:attr:`CacheWriter.timings` adds them up per phase. Saving every few frames instead of every frame was measured
too, and is slower for large frames (the unsaved samples pile up in memory), so it is not offered.

``pxr`` is imported inside the functions that need it, so ``import hairwarp`` does not load USD.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = [
    "CacheWriter",
    "UsdFileError",
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


def _vec3f(values: np.ndarray):
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float32))


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
    the exception then propagates.

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

    def __init__(self, path, *, fps: float, start_frame: int = 0, meters_per_unit: float = 1.0, up_axis: str = "Z",
                 comment: str = ""):
        self.path = Path(path).absolute()
        _check_suffix(self.path)
        _check_stage_units(self.path, up_axis, meters_per_unit)
        if not (np.isfinite(fps) and fps > 0.0):
            raise UsdFileError(f"{self.path}: fps must be a positive number, not {fps!r}")
        self.fps = float(fps)
        self.timings = {"check": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0}
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
        self._curves: dict[str, dict] = {}
        self._meshes: dict[str, dict] = {}
        self._closed = False
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
        prim_path = f"{HAIR_PATH}/{name}"
        curves = _define_curves(self._stage, prim_path, counts, w / self.meters_per_unit, interp, basis=basis,
                                kind=kind, purpose=purpose)
        self._curves[name] = {
            "schema": curves,
            "points": curves.CreatePointsAttr(),
            "velocities": None,
            "extent": curves.CreateExtentAttr(),
            "vertex_count": int(counts.sum()),
            "half_width": 0.5 * float(w.max()) / self.meters_per_unit,
        }
        return prim_path

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
        from pxr import Gf, UsdGeom, Vt

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
        if not self._stage.GetPrimAtPath(COLLIDERS_PATH):
            UsdGeom.Xform.Define(self._stage, COLLIDERS_PATH)
        prim_path = f"{COLLIDERS_PATH}/{name}"
        mesh = UsdGeom.Mesh.Define(self._stage, prim_path)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.astype(np.int32).ravel()))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([MESH_COLOR]))
        # The given points are the default value; an animated mesh's time samples override it.
        points_attr = mesh.CreatePointsAttr(_vec3f(pts))
        extent_attr = mesh.CreateExtentAttr(_vec3f(np.stack([lo, hi])))
        xform_op = mesh.AddTransformOp()
        xform_op.Set(Gf.Matrix4d(1.0))
        self._meshes[name] = {
            "path": prim_path,
            "points": points_attr,
            "extent": extent_attr,
            "xform": xform_op,
            "animated": bool(animated_points),
            "vertex_count": len(pts),
        }
        return prim_path

    # --- frames ----------------------------------------------------------------------------------------------

    def write_frame(self, frame: int, curves: dict, xforms: dict | None = None, mesh_points: dict | None = None):
        """Write one frame at time code ``frame``.

        Args:
            frame: frame number; larger than the last one written and not below ``start_frame``.
            curves: name -> (points (N, 3), velocities (N, 3) or None), world metres and metres per second, Z up,
                for every curves prim added. A prim given velocities in its first frame needs them in every frame.
            xforms: mesh name -> 4x4 world matrix, column-vector convention (``p_world = M @ [p, 1]``). A mesh left
                out of a frame has no sample there: USD interpolates between its neighbouring samples.
            mesh_points: mesh name -> (V, 3) points [m] in the mesh frame, for meshes added with animated_points.
        """
        from pxr import Gf, Usd

        t_start = time.perf_counter()
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

        # Validate everything before writing anything, so a bad frame leaves no partial samples behind.
        staged = []
        for name, value in curves.items():
            entry = self._curves[name]
            pts, vel = value if isinstance(value, tuple | list) else (value, None)
            p, lo, hi = self._points(pts, entry["vertex_count"], f"{where}: curves {name!r} points")
            v = None
            if vel is not None:
                v = self._points(vel, entry["vertex_count"], f"{where}: curves {name!r} velocities", bounds=False)[0]
            if self._frames and (v is None) != (entry["velocities"] is None):
                state = "has" if entry["velocities"] is not None else "has no"
                raise UsdFileError(f"{where}: curves {name!r} {state} velocities in earlier frames; keep it the same")
            staged.append((entry, p, v, lo, hi))
        mats = {}
        for name, m in xforms.items():
            m = np.asarray(m, dtype=np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise UsdFileError(f"{where}: xform of mesh {name!r} must be a finite 4x4 matrix")
            mats[name] = self._matrix(m)
        mesh_pts = {}
        for name, pts in mesh_points.items():
            if not self._meshes[name]["animated"]:
                raise UsdFileError(f"{where}: mesh {name!r} was not added with animated_points=True")
            mesh_pts[name] = self._points(pts, self._meshes[name]["vertex_count"], f"{where}: mesh {name!r} points")

        t_checked = time.perf_counter()
        values = []
        for entry, p, v, lo, hi in staged:
            h = entry["half_width"]
            values.append((entry, _vec3f(p), None if v is None else _vec3f(v), _vec3f(np.stack([lo - h, hi + h]))))
        mesh_values = {name: (_vec3f(p), _vec3f(np.stack([lo, hi]))) for name, (p, lo, hi) in mesh_pts.items()}
        t_converted = time.perf_counter()

        t = Usd.TimeCode(frame)
        for entry, p, v, extent in values:
            entry["points"].Set(p, t)
            if v is not None:
                if entry["velocities"] is None:
                    entry["velocities"] = entry["schema"].CreateVelocitiesAttr()
                entry["velocities"].Set(v, t)
            entry["extent"].Set(extent, t)
        for name, m in mats.items():
            self._meshes[name]["xform"].Set(Gf.Matrix4d(m.T.tolist()), t)
        for name, (p, extent) in mesh_values.items():
            self._meshes[name]["points"].Set(p, t)
            self._meshes[name]["extent"].Set(extent, t)
        del values, mesh_values
        self._frames.append(frame)
        t_set = time.perf_counter()
        if self._incremental:
            self._set_time_range()
            self._layer.Save()
        t_end = time.perf_counter()
        self.timings["check"] += t_checked - t_start
        self.timings["convert"] += t_converted - t_checked
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
        self._curves.clear()
        self._meshes.clear()
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
        lo = np.array([a[:, i].min() for i in range(3)])
        hi = np.array([a[:, i].max() for i in range(3)])
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
