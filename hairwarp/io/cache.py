"""The animation cache writer: one USD layer per frame, assembled with value clips.

Files of a finished cache ``out/tiny.usdc`` (``output.layout = "clips"``, the default)::

    out/tiny.usdc                        root layer: stage metadata, the topology as a sublayer, /World's clips
    out/tiny.clips/topology.usdc         what does not change: prims, curve counts, widths, mesh faces and points
    out/tiny.clips/manifest.usdc         the attributes the clips animate (USD's clip manifest)
    out/tiny.clips/000000.usdc ...       the time samples, one layer per frame (or per run of small frames)

Value clips are core USD composition, so every USD client reads the cache as one stage. While the run goes on all of
it lives in ``out/tiny.partial/`` (see :mod:`hairwarp.io.cache_folder`): a frame's layer is written in memory,
exported under a temporary name, fsynced and renamed into place, then the root is rewritten the same way to name it.
That commit runs in a thread while the caller simulates the next frame, and the next frame's commit starts only once
it is done, so frames become complete one at a time, in order. The root there is a valid cache of every complete
frame at any moment, and a stopped run leaves it; :meth:`CacheWriter.close` moves the cache to the output path,
replacing the old one only then. The root is a few hundred bytes, so rewriting it per frame costs nothing, and
nothing is appended to a file already written, so the cache grows with its frames (the crate format appended every
sample again on each save).

Size. A crate file costs about 1.1 KiB of its own besides the samples; for frames smaller than
``CHUNK_BYTES`` :meth:`CacheWriter.close` gathers consecutive frame layers into one clip each, so a cache of small
frames stays within a few percent of the same stage flattened into one file. ``output.layout = "single"`` flattens
the finished cache into the one file at the output path instead.

Cost of a frame. The writer takes float32, C-contiguous (N, 3) arrays without copying them (a Z-up, metre stage);
the time goes to the finiteness and extent checks, to building the ``Vt`` arrays that USD stores (one ``memmove``
into a fresh array, see :func:`hairwarp.io.usd_common._vec3f`) and to the layer's export and fsync, bound by the
disk. The caller does the first two and the frame layer's export (usd-core's export holds the GIL; run in the
commit thread it also took a core from the simulation's threads, 3-4 ms a frame more at 10,000 strands on 2 cores);
the commit thread waits on the fsyncs, which release the GIL, renames and rewrites the root while the simulation
runs. :attr:`CacheWriter.timings` adds them up per phase.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from hairwarp.io.cache_folder import CacheFolder, layer_markers
from hairwarp.io.usd_common import (
    COLLIDERS_PATH,
    DEFAULT_WIDTHS,
    HAIR_PATH,
    MESH_COLOR,
    ROOT_PATH,
    UsdFileError,
    _check_stage_units,
    _check_suffix,
    _column_bounds,
    _conversion,
    _define_curves,
    _extent,
    _new_stage,
    _vec3f,
    _vertex_normals,
    _vertex_widths,
)

__all__ = ["CHUNK_BYTES", "LAYOUTS", "CacheWriter", "cache_bytes"]

LAYOUTS = ("clips", "single")
"""``output.layout``: a root layer with one clip layer per frame, or one flattened file."""

CHUNK_BYTES = 1 << 20
"""Frame layers smaller than this are gathered into clips of about this size when the cache is closed."""

_FRAME_OVERHEAD = 4096
"""Bytes a frame layer may take besides its arrays (crate tables; 1.1 KiB measured), for the space check."""


class CacheWriter:
    """Writes a time-sampled USD animation cache of hair curves and collider meshes, one layer per frame.

    Points are given in world metres, Z up, and stored at the time code ``frame``; ``timeCodesPerSecond`` and
    ``framesPerSecond`` are both ``fps``, so velocities are per second. Usage::

        with CacheWriter("out/hair.usdc", fps=24) as cache:
            cache.add_curves("dense", counts, widths=(1e-4, 2e-5), basis="catmullRom")
            cache.add_mesh("head", vertices, faces)
            for frame in range(48):
                cache.write_frame(frame, {"dense": (points, velocities)}, xforms={"head": head_matrix})

    The cache goes to ``path`` only when :meth:`close` runs (the ``with`` block ends without an exception). An
    exception leaves the frames written so far as a valid cache at :attr:`partial_path`, the cache at ``path``
    untouched, and propagates. :class:`hairwarp.io.background.BackgroundCacheWriter` has the same interface and
    writes in a second process.

    Args:
        path: destination, ending in .usd, .usda or .usdc (every layer of the cache takes its format); its folder
            is created if missing.
        fps: frames per second of the cache.
        start_frame: the first frame that may be written; also the start and end time code of a cache with no frame.
        meters_per_unit: stage unit, in metres.
        up_axis: "Z" (the simulator's) or "Y"; data are rotated into it.
        comment: appended to the layer's documentation string.
        layout: "clips" (a root layer and its clip layers) or "single" (flattened into one file at close).
        resume: continue the cache a stopped run left in the working folder after its last complete frame
            (:attr:`resumed_after`); the next frame written must follow it.
        owner: take the lock of the working folder and prepare it (False in a background writer's process, whose
            caller holds the lock).
        pipelined: commit each frame (fsync, rename, rewrite the root) in a thread while the caller goes on
            (see :meth:`write_frame`); False commits it before :meth:`write_frame` returns.

    Attributes:
        timings: seconds spent writing frames so far, per phase: in the caller's :meth:`write_frame` ``check``
            (validation, unit conversion, extent), ``convert`` (numpy to ``Vt`` arrays), ``set`` (authoring the
            samples) and ``wait`` (for the previous frame's commit); ``save`` (the frame's export in the caller, then
            fsyncs, renames and the root in the commit thread, complete once :meth:`flush` or :meth:`close`
            returns).
        folder: the :class:`hairwarp.io.cache_folder.CacheFolder` (lock, checkpoints, what an earlier run left).
        resumed_after: the last frame of the resumed run, or None.

    Raises:
        UsdFileError: bad arguments, an output that is a folder or cannot be written.
        hairwarp.io.cache_folder.CacheBusyError: another live run writes the same cache.
    """

    _EXTENTS_IN_CALLER = True
    """Whether :meth:`write_frame` computes the extents while checking (else :meth:`_author_frame` does)."""

    def __init__(self, path, *, fps: float, start_frame: int = 0, meters_per_unit: float = 1.0, up_axis: str = "Z",
                 comment: str = "", layout: str = "clips", resume: bool = False, owner: bool = True,
                 pipelined: bool = True):
        self._setup(path, fps, start_frame, meters_per_unit, up_axis, layout, comment)
        self.timings = {"check": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0, "wait": 0.0}
        self._pipelined = bool(pipelined)
        if owner:
            self.folder.acquire()
            try:
                self.resumed_after = self.folder.prepare(resume)
            except BaseException:
                self.folder.release()
                raise
        else:
            span = self.folder.frame_range() if resume else None
            self.resumed_after = span[1] if span else None
        self._owner = owner
        if self.resumed_after is not None:
            self._frames = list(range(self.folder.frame_range()[0], self.resumed_after + 1))
        self._resumed_frames = len(self._frames)

    def _setup(self, path, fps, start_frame, meters_per_unit, up_axis, layout, comment) -> None:
        """Check the arguments and set what both writers keep: units, the frames written, the prims declared."""
        self.path = Path(path).absolute()
        _check_suffix(self.path)
        if layout not in LAYOUTS:
            raise UsdFileError(f"{self.path}: layout must be one of {', '.join(LAYOUTS)}, not {layout!r}")
        self.layout = layout
        self.folder = CacheFolder(self.path)
        self._suffix = self.path.suffix.lower()
        self._doc = f"hairwarp animation cache: hair curves under {HAIR_PATH}, colliders under {COLLIDERS_PATH}."
        if comment:
            self._doc += "\n" + comment
        self._topology: list[tuple[str, dict]] = []
        self._topology_written = False
        self._half_widths: dict[str, float] = {}
        self._mesh_faces: dict[str, np.ndarray] = {}  # triangles of each mesh, for per-frame normals
        self._resumed_frames = 0
        self.resumed_after = None
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
        self._frames: list[int] = []  # complete frames: on disk and named by the root (inline writer)
        self._pending_frame: int | None = None  # the frame the commit thread is saving
        self._commit_thread: threading.Thread | None = None
        self._commit_error: BaseException | None = None
        self._vt_used: dict = {}  # the Vt arrays of the last frame and of the one before, by (prim, attribute)
        self._vt_spare: dict = {}
        # name -> {"vertex_count", "half_width" (stage units), "velocities" (True once given)}
        self._curves: dict[str, dict] = {}
        # name -> {"vertex_count", "animated"}
        self._meshes: dict[str, dict] = {}
        self._closed = False

    # --- setup -----------------------------------------------------------------------------------------------

    def add_curves(self, name: str, curve_vertex_counts, *, widths=DEFAULT_WIDTHS, kind: str = "dense",
                   basis: str = "linear", purpose: str = "default", root_uv=None, strand_ids=None) -> str:
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
            purpose: the UsdGeom purpose; "guide" hides the curves from renders and from viewports that hide guides,
                and marks them as simulation guides for Unreal (``primvars:groom_guide`` = 1).
            root_uv: optional (C, 2) texture coordinates of each curve's root on the scalp, written as
                ``primvars:st`` and ``primvars:groom_root_uv`` (uniform, one per curve).
            strand_ids: optional (C,) ints for ``primvars:groom_id``; default 0 .. C-1.

        Returns:
            The prim path.
        """
        where = f"{self.path}: curves {name!r}"
        self._check_open()
        self._check_name(name, where)
        if self._given_count() > self._resumed_frames:
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
        uv = ids = None
        if root_uv is not None:
            uv = np.asarray(root_uv, dtype=np.float64)
            if uv.shape != (len(counts), 2) or not np.all(np.isfinite(uv)):
                raise UsdFileError(f"{where}: root_uv must be a finite ({len(counts)}, 2) array, got {uv.shape}")
        if strand_ids is not None:
            ids = np.asarray(strand_ids)
            if ids.shape != (len(counts),) or not np.issubdtype(ids.dtype, np.integer):
                raise UsdFileError(f"{where}: strand_ids must be {len(counts)} ints")
        spec = {"name": name, "counts": counts, "widths": w / self.meters_per_unit, "interp": interp, "basis": basis,
                "kind": kind, "purpose": purpose, "root_uv": uv, "strand_ids": ids}
        self._author_curves(spec)
        self._curves[name] = {"vertex_count": int(counts.sum()),
                              "half_width": 0.5 * float(w.max()) / self.meters_per_unit, "velocities": None}
        return f"{HAIR_PATH}/{name}"

    def add_mesh(self, name: str, points, face_vertex_indices, *, animated_points: bool = False,
                 purpose: str = "proxy") -> str:
        """Declare a triangle mesh ``/World/Colliders/<name>`` with a time-sampled transform and vertex normals.

        Args:
            name: prim name, a valid USD identifier.
            points: (V, 3) vertices [m] in the mesh's own frame (Z up); for an animated mesh, its rest pose.
            face_vertex_indices: (F, 3) vertex indices of the triangles.
            animated_points: the points change per frame and are given to :meth:`write_frame` in ``mesh_points``
                (the normals are then written per frame too).
            purpose: the UsdGeom purpose: "proxy" (default) shows the collider in viewports and keeps it out of
                renders; "render" or "default" renders it.

        Returns:
            The prim path.
        """
        where = f"{self.path}: mesh {name!r}"
        self._check_open()
        self._check_name(name, where)
        if self._given_count() > self._resumed_frames:
            raise UsdFileError(f"{where}: meshes must be added before the first frame is written")
        pts, lo, hi = self._points(points, None, where)
        faces = np.asarray(face_vertex_indices)
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise UsdFileError(f"{where}: face_vertex_indices must be an (F, 3) array of ints")
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise UsdFileError(f"{where}: face_vertex_indices out of range for {len(pts)} points")
        if purpose not in ("default", "render", "proxy"):
            raise UsdFileError(f"{where}: purpose must be default, render or proxy, not {purpose!r}")
        spec = {"name": name, "points": pts, "extent": np.stack([lo, hi]).astype(np.float32),
                "faces": faces.astype(np.int32), "animated": bool(animated_points), "purpose": purpose}
        self._author_mesh(spec)
        self._meshes[name] = {"animated": bool(animated_points), "vertex_count": len(pts)}
        return f"{COLLIDERS_PATH}/{name}"


    def _author_curves(self, spec: dict) -> None:
        """Keep a checked ``add_curves`` for the topology layer, written with the first frame."""
        self._topology.append(("curves", spec))
        self._half_widths[spec["name"]] = 0.5 * float(np.max(spec["widths"]))  # stage units

    def _author_mesh(self, spec: dict) -> None:
        """Keep a checked ``add_mesh`` (points in stage units, float32) for the topology layer."""
        self._topology.append(("mesh", spec))
        self._mesh_faces[spec["name"]] = spec["faces"]

    # --- frames ----------------------------------------------------------------------------------------------

    def write_frame(self, frame: int, curves: dict, xforms: dict | None = None, mesh_points: dict | None = None,
                    checkpoint: dict | None = None):
        """Write one frame at time code ``frame``.

        Every argument is checked before anything is written: a bad frame raises :class:`UsdFileError` naming the file,
        the prim and the frame, and leaves the cache as it was. The arrays are copied into the frame's layer before this
        returns, so the caller may overwrite them at once. The layer is exported to a temporary file here, then fsynced,
        renamed into place and named in the root by a commit thread while the caller goes on (the simulation of the next
        frame); the next call, :meth:`close`, :meth:`flush` and :meth:`abandon` wait for it first, so frames are
        committed one at a time, in order, and the root always names complete frames only. A failed export (a full disk,
        an I/O error) raises here, a failed commit in the next of those calls (see :meth:`flush`). With
        ``pipelined=False`` the frame is complete on disk when this returns.

        Args:
            frame: frame number; larger than the last one written and not below ``start_frame``.
            curves: name -> (points (N, 3), velocities (N, 3) or None), world metres and metres per second, Z up,
                for every curves prim added. A prim given velocities in its first frame needs them in every frame.
            xforms: mesh name -> 4x4 world matrix, column-vector convention (``p_world = M @ [p, 1]``), for every
                mesh added (the frame's layer holds the frame's value of every animated attribute).
            mesh_points: mesh name -> (V, 3) points [m] in the mesh frame, for meshes added with animated_points.
            checkpoint: name -> array: state to resume from after this frame, stored beside its layer
                (``numpy.savez``) before the root names the frame; the previous frame's is then removed.

        Raises:
            UsdFileError: a bad frame.
            hairwarp.io.cache_folder.CacheWriteError: the disk is full or failed, saving this frame or the one
                before; the frames before the failed one stay complete.
        """
        self._raise_commit_failure()
        t_start = time.perf_counter()
        prepared = self._prepare_frame(frame, curves, xforms, mesh_points)
        self.timings["check"] += time.perf_counter() - t_start
        state = None
        if checkpoint is not None:  # packed here, written with the frame's layer (by the commit thread)
            state = (prepared["frame"], self.folder.pack_checkpoint(prepared["frame"], checkpoint))
        self._author_frame(prepared, prune=checkpoint is not None, state=state)
        for name, _, v, _ in prepared["curves"]:
            self._curves[name]["velocities"] = v is not None

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
        last = self._pending_frame if self._pending_frame is not None else self.last_frame
        if last is not None and frame <= last:
            raise UsdFileError(f"{where}: frames must increase; the last one written was {last}")
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
            if entry["velocities"] is not None and (v is not None) != entry["velocities"]:
                state = "has" if entry["velocities"] else "has no"
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


    def _author_frame(self, prepared: dict, converted=None, prune: bool = False, state=None) -> None:
        """Author the layer of a prepared frame and export it, then commit it (:meth:`_commit_frame`): in the commit
        thread once the previous frame's commit is done, or here (export included) without ``pipelined``.

        Args:
            prepared: what :meth:`_prepare_frame` returned.
            converted: called once the arrays have been copied into ``Vt`` arrays (the inputs are free again).
            prune: remove the checkpoints before this frame once the root names it.
            state: ``(frame, bytes)`` of the frame's checkpoint (``CacheFolder.pack_checkpoint``), written and put
                in place before the root names the frame, or None.
        """
        from pxr import Gf, Sdf

        t_start = time.perf_counter()
        frame = prepared["frame"]
        if not self._topology_written:
            self._write_topology(prepared)
        # The Vt arrays of two frames ago are reused: that frame's commit is done (the one before this frame's
        # started only after it), so nothing reads them; a fresh array costs page faults (4x the copy at 100 MB).
        spare, used = self._vt_spare, {}

        def vt(key, a, spare=spare, used=used):
            used[key] = _vec3f(a, out=spare.get(key))
            return used[key]

        values = [(name, vt((name, "points"), p), None if v is None else vt((name, "velocities"), v),
                   _vec3f(_extent(*_column_bounds(p), self._half_widths[name]) if ext is None else ext))
                  for name, p, v, ext in prepared["curves"]]
        mesh_values = {name: (vt((name, "mesh"), p), _vec3f(_extent(*_column_bounds(p), 0.0) if ext is None else ext),
                              vt((name, "normals"), _vertex_normals(p, self._mesh_faces[name])))
                       for name, (p, ext) in prepared["meshes"].items()}
        self._vt_spare, self._vt_used = self._vt_used, used
        del spare
        nbytes = sum(a.nbytes for _, p, v, _ in prepared["curves"] for a in (p, v) if a is not None)
        nbytes += sum(p.nbytes for p, _ in prepared["meshes"].values())
        t_converted = time.perf_counter()
        if converted is not None:
            converted()
        layer = Sdf.Layer.CreateAnonymous(f"frame{self._suffix}")
        t = float(frame)
        types = Sdf.ValueTypeNames
        for name, p, v, extent in values:
            spec = Sdf.CreatePrimInLayer(layer, f"{HAIR_PATH}/{name}")
            _sample(layer, spec, "points", types.Point3fArray, t, p)
            if v is not None:
                _sample(layer, spec, "velocities", types.Vector3fArray, t, v)
            _sample(layer, spec, "extent", types.Float3Array, t, extent)
        for name, mat in prepared["xforms"].items():
            spec = Sdf.CreatePrimInLayer(layer, f"{COLLIDERS_PATH}/{name}")
            _sample(layer, spec, "xformOp:transform", types.Matrix4d, t, Gf.Matrix4d(mat.T.tolist()))
        for name, (p, extent, normals) in mesh_values.items():
            spec = Sdf.CreatePrimInLayer(layer, f"{COLLIDERS_PATH}/{name}")
            _sample(layer, spec, "points", types.Point3fArray, t, p)
            _sample(layer, spec, "extent", types.Float3Array, t, extent)
            _sample(layer, spec, "normals", types.Normal3fArray, t, normals)
        del values, mesh_values
        t_set = time.perf_counter()
        self.timings["convert"] += t_converted - t_start
        self.timings["set"] += t_set - t_converted
        if not self._pipelined:
            self._wait_commit()
            self._commit_frame(frame, [layer], nbytes, prune, state)
            return
        # The export runs here, beside the previous frame's fsyncs: it holds Python's lock anyway, and in the commit
        # thread it would also take a core from the simulation's threads while they need both.
        dest = self.folder.frame_layer(frame)
        try:
            tmp = self.folder.export_temporary(layer, dest, nbytes + _FRAME_OVERHEAD, f"frame {frame}")
        finally:
            del layer
        self.timings["save"] += time.perf_counter() - t_set
        try:
            self._wait_commit()
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        held = [tmp]
        self._pending_frame = frame
        self._commit_thread = threading.Thread(target=self._commit_in_thread,
                                               args=(frame, held, nbytes, prune, state),
                                               name=f"hairwarp cache commit {frame}")
        self._commit_thread.start()

    def _commit_frame(self, frame: int, held: list, nbytes: int, prune: bool, state=None) -> None:
        """Save the frame in ``held`` (its layer, or the temporary file it was exported to) fsynced and renamed into
        place, and its checkpoint (``state``, as :meth:`_author_frame` takes it) before it, then rewrite the root to
        name it; only then is the frame complete (:attr:`last_frame`) and the checkpoints before it removed."""
        t_start = time.perf_counter()
        dest, what = self.folder.frame_layer(frame), f"frame {frame}"
        try:
            if state is not None:
                self.folder.commit_checkpoint(*state)
            done = held.pop()
            if isinstance(done, Path):
                self.folder.commit(done, dest, what)
            else:
                self.folder.export_layer(done, dest, nbytes + _FRAME_OVERHEAD, what)
            del done
            self._write_root(self._frames + [frame])
            self._frames.append(frame)
            if prune:
                self.folder.prune_checkpoints(frame)
        finally:
            held.clear()
            self.timings["save"] += time.perf_counter() - t_start

    def _commit_in_thread(self, frame: int, held: list, nbytes: int, prune: bool, state=None) -> None:
        """The commit thread's body: any failure is kept for :meth:`_wait_commit` to raise in the caller."""
        try:
            self._commit_frame(frame, held, nbytes, prune, state)
        except BaseException as exc:  # noqa: BLE001 - handed over to the caller's thread
            self._commit_error = exc

    def _wait_commit(self) -> None:
        """Wait for the frame in the commit thread; raise its failure, as often as asked (a cache whose frame
        failed takes no further frame: its root could not name them all)."""
        thread = self._commit_thread
        if thread is not None:
            t_start = time.perf_counter()
            thread.join()
            self._commit_thread = None
            self._pending_frame = None
            self.timings["wait"] += time.perf_counter() - t_start
        self._raise_commit_failure()

    def _raise_commit_failure(self) -> None:
        if self._commit_error is not None:
            raise self._commit_error.with_traceback(None)

    def _given_count(self) -> int:
        """Frames given to :meth:`write_frame` so far (complete or being committed), resumed ones included."""
        return len(self._frames) + (self._pending_frame is not None)

    def flush(self) -> None:
        """Wait until every frame given so far is complete on disk and named in the root.

        Raises:
            hairwarp.io.cache_folder.CacheWriteError: a frame's commit failed (raised again by every later call but
                :meth:`abandon`); the frames before it stay complete.
        """
        self._check_open()
        self._wait_commit()

    def _write_topology(self, first: dict) -> None:
        """Write the topology layer (every prim and its static values) and the clip manifest (the attributes the
        frame layers animate, as known from the first frame)."""
        from pxr import Gf, Sdf, UsdGeom, Vt

        self.folder.clips.mkdir(exist_ok=True)
        layer, stage = _new_stage(None, up_axis=self.up_axis, meters_per_unit=self.meters_per_unit, doc=self._doc,
                                  suffix=self._suffix)
        manifest = Sdf.Layer.CreateAnonymous(f"manifest{self._suffix}")
        types = Sdf.ValueTypeNames
        nbytes = 0
        velocities = {name for name, _, v, _ in first["curves"] if v is not None}
        for kind, spec in self._topology:
            name = spec["name"]
            if kind == "curves":
                path = f"{HAIR_PATH}/{name}"
                curves = _define_curves(stage, path, spec["counts"], spec["widths"], spec["interp"],
                                        basis=spec["basis"], kind=spec["kind"], purpose=spec["purpose"],
                                        root_uv=spec.get("root_uv"), strand_ids=spec.get("strand_ids"))
                curves.CreatePointsAttr()
                curves.CreateExtentAttr()
                animated = [("points", types.Point3fArray), ("extent", types.Float3Array)]
                if name in velocities:
                    curves.CreateVelocitiesAttr()
                    animated.append(("velocities", types.Vector3fArray))
                nbytes += spec["counts"].nbytes + spec["widths"].nbytes
            else:
                if not stage.GetPrimAtPath(COLLIDERS_PATH):
                    UsdGeom.Xform.Define(stage, COLLIDERS_PATH)
                path = f"{COLLIDERS_PATH}/{name}"
                faces = spec["faces"]
                mesh = UsdGeom.Mesh.Define(stage, path)
                mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
                mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces).ravel()))
                mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
                mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([MESH_COLOR]))
                # The given points are the default value; an animated mesh's clip samples override it.
                mesh.CreatePointsAttr(_vec3f(spec["points"]))
                mesh.CreateExtentAttr(_vec3f(spec["extent"]))
                mesh.CreateNormalsAttr(_vec3f(_vertex_normals(spec["points"], faces)))
                mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
                mesh.CreatePurposeAttr(spec.get("purpose", "proxy"))
                mesh.AddTransformOp().Set(Gf.Matrix4d(1.0))
                animated = [("xformOp:transform", types.Matrix4d)]
                if spec["animated"]:
                    animated += [("points", types.Point3fArray), ("extent", types.Float3Array),
                                 ("normals", types.Normal3fArray)]
                nbytes += 2 * faces.nbytes + spec["points"].nbytes
            prim = Sdf.CreatePrimInLayer(manifest, path)
            for attr, type_name in animated:
                Sdf.AttributeSpec(prim, attr, type_name)
        del stage
        self.folder.export_layer(layer, self.folder.clips / f"topology{self._suffix}", nbytes + 65536,
                                 "the cache's topology")
        self.folder.export_layer(manifest, self.folder.clips / f"manifest{self._suffix}", 65536,
                                 "the cache's clip manifest")
        self._topology_written = True

    def _root_layer(self, frames: list[int], clips: dict | None, chunked: bool = False):
        """The root layer of ``frames``: stage metadata, the topology sublayer, and /World's clip set ``default``."""
        from pxr import Sdf

        import hairwarp

        layer = Sdf.Layer.CreateAnonymous(f"root{self._suffix}")
        layer.documentation = self._doc
        first = frames[0] if frames else self.start_frame
        last = frames[-1] if frames else self.start_frame
        data = {"creator": f"hairwarp {hairwarp.__version__}"}
        if frames:
            data.update(layer_markers(first, last, chunked))
        layer.customLayerData = data
        layer.pseudoRoot.SetInfo("upAxis", self.up_axis)
        layer.pseudoRoot.SetInfo("metersPerUnit", self.meters_per_unit)
        layer.timeCodesPerSecond = self.fps
        layer.framesPerSecond = self.fps
        layer.startTimeCode = first
        layer.endTimeCode = last
        layer.defaultPrim = ROOT_PATH.strip("/")
        if self._topology_written:
            layer.subLayerPaths.append(f"./{self.folder.clips_name}/topology{self._suffix}")
        if clips is not None:
            clips = {"primPath": ROOT_PATH,
                     "manifestAssetPath": Sdf.AssetPath(f"./{self.folder.clips_name}/manifest{self._suffix}"),
                     **clips}
            Sdf.CreatePrimInLayer(layer, ROOT_PATH).SetInfo("clips", {"default": clips})
        return layer

    def _write_root(self, frames: list[int]) -> None:
        """Rewrite the working root to name the frame layers ``frames`` (consecutive, on disk), through a template
        clip set."""
        clips = None
        if frames:
            clips = {"templateAssetPath": f"./{self.folder.clips_name}/######{self._suffix}",
                     "templateStartTime": float(frames[0]), "templateEndTime": float(frames[-1]),
                     "templateStride": 1.0}
        self.folder.export_layer(self._root_layer(frames, clips), self.folder.root, 65536, "the cache's root layer")

    def _gather_small_frames(self) -> None:
        """Gather runs of consecutive frame layers smaller than :data:`CHUNK_BYTES` into one clip each, name them
        in the root (explicit clip lists), then remove the frame layers; a cache of small frames then costs a
        crate file's tables once per chunk instead of once per frame."""
        from pxr import Sdf, Vt

        frames = self._frames
        sizes = [self.folder.frame_layer(f).stat().st_size for f in frames]
        per_chunk = max(1, int(CHUNK_BYTES // max(1, int(np.median(sizes)))))
        if per_chunk < 2 or len(frames) < 2:
            return
        assets, active = [], []
        for i in range(0, len(frames), per_chunk):
            group = frames[i:i + per_chunk]
            chunk = Sdf.Layer.CreateAnonymous(f"chunk{self._suffix}")
            for k, f in enumerate(group):
                src = Sdf.Layer.OpenAsAnonymous(str(self.folder.frame_layer(f)))
                if k == 0:
                    Sdf.CopySpec(src, ROOT_PATH, chunk, ROOT_PATH)
                    attrs = []
                    src.Traverse(ROOT_PATH, lambda p, attrs=attrs: attrs.append(p) if p.IsPropertyPath() else None)
                    continue
                for p in attrs:
                    for t in src.ListTimeSamplesForPath(p):
                        chunk.SetTimeSample(p, t, src.QueryTimeSample(p, t))
            name = f"{group[0]:06d}-{group[-1]:06d}{self._suffix}"
            self.folder.export_layer(chunk, self.folder.clips / name, sum(sizes[i:i + per_chunk]) + 65536,
                                     f"frames {group[0]}-{group[-1]}")
            assets.append(f"./{self.folder.clips_name}/{name}")
            active.append((float(group[0]), float(len(assets) - 1)))
        clips = {"assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(a) for a in assets]),
                 "active": Vt.Vec2dArray(active),
                 "times": Vt.Vec2dArray([(float(frames[0]), float(frames[0])), (float(frames[-1]), float(frames[-1]))])}
        self.folder.export_layer(self._root_layer(frames, clips, chunked=True), self.folder.root,
                                 65536 + 64 * len(assets), "the cache's root layer")
        for f in frames:
            self.folder.frame_layer(f).unlink()

    @property
    def frames_written(self) -> int:
        """Number of frames the cache holds (those of a resumed run included)."""
        return len(self._frames)

    @property
    def last_frame(self) -> int | None:
        """The last complete frame, or None."""
        return self._frames[-1] if self._frames else None

    @property
    def partial_path(self) -> Path:
        """The working root layer: a valid cache of every complete frame while the run goes on or after it stopped."""
        return self.folder.root

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has put the cache in place."""
        return self._closed

    def close(self, keep_lock: bool = False) -> Path:
        """Finish the cache (gather small frames, or flatten for layout "single") and move it to ``path``,
        replacing the cache there. Idempotent.

        Args:
            keep_lock: hold the output's lock until :meth:`release`, for what the run writes beside the cache
                (its preview), so that a second run cannot start on the output in between.

        Returns:
            The destination path.
        """
        if self._closed:
            return self.path
        self._wait_commit()
        if not self._topology_written:
            self._write_topology({"curves": []})
            self._write_root(self._frames)
        self._finish()  # also in a background writer's process, the one that holds the layers
        self._closed = True
        if not keep_lock:
            self.release()
        return self.path

    def release(self) -> None:
        """Release the output's lock (after ``close(keep_lock=True)``) and remove the emptied working folder.
        Idempotent."""
        if self._owner:
            self.folder.release()

    def _finish(self) -> None:
        from pxr import Usd

        from hairwarp.io.usd_common import _reload_if_open

        flat = None
        if self.layout == "single":
            stage = Usd.Stage.Open(str(self.folder.root))
            layer = stage.Flatten()
            layer.documentation = self._doc
            del stage
            flat = self.folder.dir / f"{self.path.stem}.flat{self._suffix}"
            needed = sum(p.stat().st_size for p in self.folder.clips.iterdir()) + 65536
            self.folder.export_layer(layer, flat, needed, "the flattened cache")
        elif not _is_chunked(self.folder.root) and self._frames:
            self._gather_small_frames()
        self.folder.finish(flat)
        _reload_if_open(self.path)
        _reload_clips(self.path.parent / self.folder.clips_name)

    def abandon(self) -> Path | None:
        """Stop without finishing: the frames written so far stay at :attr:`partial_path` (returned; None when no
        frame was complete and nothing is kept), the cache at ``path`` untouched, and the lock is released."""
        if self._closed:
            return None
        try:
            self._wait_commit()  # the frame in flight is complete or failed before the lock goes
        except Exception:  # noqa: BLE001 - the frames before it are kept; the caller is stopping already
            pass
        self._closed = True
        if self._owner:
            self.folder.release()
        return self.folder.root if self.folder.root.exists() else None

    def __enter__(self) -> CacheWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abandon()
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



def _sample(layer, prim_spec, name: str, type_name, time: float, value) -> None:
    """Author one time sample of attribute ``name`` on a prim spec of an in-memory layer."""
    from pxr import Sdf

    attr = prim_spec.attributes.get(name) or Sdf.AttributeSpec(prim_spec, name, type_name)
    layer.SetTimeSample(attr.path, time, value)


def _is_chunked(root: Path) -> bool:
    from pxr import Sdf

    return bool(Sdf.Layer.OpenAsAnonymous(str(root)).customLayerData.get("hairwarp:chunked"))


def _reload_clips(clips_dir: Path) -> None:
    """Make clip layers of this folder still open in the process (an earlier cache) read the new files."""
    from pxr import Sdf

    prefix = str(clips_dir) + "/"
    for layer in Sdf.Layer.GetLoadedLayers():
        if layer.realPath.startswith(prefix):
            try:
                layer.Reload(force=True)
            except Exception:  # the file went with the cache it belonged to
                pass


def cache_bytes(path) -> int:
    """Bytes of a finished cache: its root file and, for layout "clips", the clip layers beside it."""
    path = Path(path)
    clips = path.with_name(path.stem + ".clips")
    return path.stat().st_size + (sum(p.stat().st_size for p in clips.iterdir()) if clips.is_dir() else 0)
