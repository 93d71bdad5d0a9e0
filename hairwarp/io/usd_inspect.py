"""Reading caches back: frames for previews, and the summary ``hairwarp info`` prints."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hairwarp.io.usd_common import (
    UsdFileError,
    _curve_arrays,
    _first_time,
    _human_bytes,
    _mesh_arrays,
    _open_stage,
    _prims,
    _stage_to_metres_z,
    _time_samples,
    _unique_names,
)

__all__ = ["describe", "read_frames"]


def read_frames(path, frames=None) -> list[dict]:
    """Curves and meshes of a cache, frame by frame, in world metres, Z up (for previews).

    Args:
        path: a cache written by :class:`CacheWriter` (any stage with BasisCurves works).
        frames: frame numbers (time codes) to read; None reads every time sample of curve points, mesh points and
            transforms (or the default time when nothing is animated).

    Returns:
        One dict per frame: ``{"frame": float, "time": seconds from the stage's start time code (a hairwarp cache's
        simulation time, whatever its ``output.start_frame``), "curves": {prim name: (points (N, 3) float64,
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
    start = stage.GetStartTimeCode() if stage.HasAuthoredTimeCodeRange() else 0.0
    curve_names = _unique_names(curve_prims)
    mesh_names = _unique_names(mesh_prims)
    out = []
    for f in frames:
        xc = UsdGeom.XformCache(float(f))
        curves = {n: _curve_arrays(p, float(f), xc, conv, path) for n, p in zip(curve_names, curve_prims, strict=True)}
        meshes = {n: _mesh_arrays(p, float(f), xc, conv) for n, p in zip(mesh_names, mesh_prims, strict=True)}
        out.append({"frame": float(f), "time": (float(f) - start) / tcps, "curves": curves, "meshes": meshes})
    return out


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
    from hairwarp.io.cache import cache_bytes

    size = cache_bytes(path)
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
