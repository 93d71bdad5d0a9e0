"""Static grooms in USD: one linear BasisCurves prim written; the BasisCurves and NurbsCurves prims of a stage
read back as polylines in metres, Z up (see :mod:`hairwarp.io.usd_common` for the layout and the conversions),
with their widths and root texture coordinates.

Curves are evaluated at their own basis, never taken control point by control point: cubic ``bezier``
(segments of 4 points sharing ends, ``vstep`` 3), ``bspline`` and ``catmullRom`` (``vstep`` 1, with the phantom end
points of wrap ``pinned``: ``P[-1] = 2 P[0] - P[1]``) are sampled :data:`SAMPLES_PER_SEGMENT` times per segment;
``NurbsCurves`` with their ``order``, ``knots`` and ``pointWeights`` (rational), as many samples per knot span,
over the valid range ``[t[k], t[n]]`` (scipy's ``BSpline``). Periodic curves are refused.

Widths (``widths`` or ``primvars:widths``, constant, uniform, varying or vertex) follow the samples: per-vertex
values are interpolated linearly in the curve parameter. Root texture coordinates are the first of
``primvars:groom_root_uv`` (Unreal), ``primvars:st``, ``primvars:surface_uv_coordinate`` (Blender) and
``primvars:uv`` (Houdini) the prim has: its uniform value, or its value at the curve's first vertex.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from hairwarp.io.usd_common import (
    HAIR_PATH,
    UsdFileError,
    _apply_linear,
    _check_stage_units,
    _check_suffix,
    _conversion,
    _curve_arrays,
    _default_permissions,
    _define_curves,
    _first_time,
    _new_stage,
    _open_stage,
    _prims,
    _reload_if_open,
    _stage_to_metres_z,
    _vec3f,
    _vertex_widths,
    _world_points,
    stage_units,
)

__all__ = ["PURPOSES", "SAMPLES_PER_SEGMENT", "read_curves", "read_groom", "write_curves"]

SAMPLES_PER_SEGMENT = 8
"""Polyline pieces per cubic segment or NURBS knot span when a curve is evaluated."""

PURPOSES = ("auto", "guide", "render", "all")
"""Which curves :func:`read_groom` takes by UsdGeom purpose (see there)."""

_UV_PRIMVARS = ("groom_root_uv", "st", "surface_uv_coordinate", "uv")


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


def read_groom(path, *, purpose: str = "auto") -> dict:
    """The curves of a stage as world polylines in metres, Z up, with their widths and root texture coordinates.

    Args:
        path: a .usd, .usda, .usdc or .usdz file.
        purpose: "guide" (curves of purpose guide), "render" (every other curve), "all", or "auto" (the guides
            when the stage has guide curves and others, as a hairwarp cache with dense hair does; else all).

    Returns:
        ``{"curves": [(n_i, 3) float64], "widths": [(n_i,) float64 diameters, m] or None when no prim has widths,
        "uv": (C, 2) float64 or None when no prim has root texture coordinates, "prims": [prim path per curve]}``.
        Curves of prims without widths get zeros when others have them; without coordinates, zeros likewise.

    Raises:
        UsdFileError: the file is missing or unreadable, has no curves prim (of that purpose), a periodic curve,
            or inconsistent curve arrays (named by prim).
    """
    from pxr import UsdGeom

    if purpose not in PURPOSES:
        raise UsdFileError(f"{path}: purpose must be one of {', '.join(PURPOSES)}, not {purpose!r}")
    stage = _open_stage(path)
    conv = _stage_to_metres_z(stage)
    _, mpu = stage_units(stage)
    prims = [p for p in _prims(stage, UsdGeom.Curves) if p.IsA(UsdGeom.BasisCurves) or p.IsA(UsdGeom.NurbsCurves)]
    if not prims:
        raise UsdFileError(f"{path}: no BasisCurves or NurbsCurves prim in the stage")
    guide = [UsdGeom.Imageable(p).ComputePurpose() == UsdGeom.Tokens.guide for p in prims]
    if purpose == "auto":
        purpose = "guide" if any(guide) and not all(guide) else "all"
    if purpose != "all":
        prims = [p for p, g in zip(prims, guide, strict=True) if g == (purpose == "guide")]
        if not prims:
            raise UsdFileError(f"{path}: no curves of purpose {purpose!r} in the stage")
    curves, widths, uvs, names = [], [], [], []
    any_width = any_uv = False
    for prim in prims:
        geom = UsdGeom.Curves(prim)
        time = _first_time(geom.GetPointsAttr())
        xf = UsdGeom.XformCache(time)
        counts = np.asarray(geom.GetCurveVertexCountsAttr().Get(time) or [], dtype=np.int64)
        pts = geom.GetPointsAttr().Get(time)
        pts = np.zeros((0, 3)) if pts is None else np.asarray(pts, dtype=np.float64)
        where = f"{path}: {prim.GetPath()}"
        if len(counts) == 0 and len(pts) == 0:
            continue  # a placeholder prim: no curves
        if np.any(counts < 1):
            raise UsdFileError(f"{where}: curveVertexCounts holds {int(counts.min())} (curve "
                               f"{int(np.argmin(counts))}); every curve needs a vertex or more")
        if counts.sum() != len(pts):
            raise UsdFileError(f"{where} has {len(pts)} points but its curveVertexCounts add up to {int(counts.sum())}")
        world = _world_points(pts, xf, prim, conv)
        w_ctrl = _control_widths(geom, counts, time, where)
        any_width |= w_ctrl is not None
        uv = _root_uv(prim, counts, time)
        any_uv |= uv is not None
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        if prim.IsA(UsdGeom.NurbsCurves):
            lines = _nurbs_polylines(UsdGeom.NurbsCurves(prim), world, counts, starts, time, where)
        else:
            lines = _basis_polylines(UsdGeom.BasisCurves(prim), world, counts, starts, time, where)
        for c, (line, u) in enumerate(lines):
            curves.append(line)
            if w_ctrl is None:
                widths.append(np.zeros(len(line)))
            else:
                wc = w_ctrl[starts[c]:starts[c] + counts[c]]
                widths.append(np.interp(u, np.linspace(0.0, 1.0, len(wc)), wc) * mpu if len(wc) > 1
                              else np.full(len(line), wc[0] * mpu))
            names.append(str(prim.GetPath()))
        uvs.append(np.zeros((len(counts), 2)) if uv is None else uv)
    if not curves:
        raise UsdFileError(f"{path}: its curves prims ({', '.join(str(p.GetPath()) for p in prims[:3])}"
                           f"{' ...' if len(prims) > 3 else ''}) hold no curves")
    return {"curves": curves, "widths": widths if any_width else None,
            "uv": np.concatenate(uvs) if any_uv else None, "prims": names}


def _control_widths(geom, counts: np.ndarray, time, where: str) -> np.ndarray | None:
    """Widths per control vertex (stage units), from constant, uniform, varying or vertex widths; None if none."""
    from pxr import UsdGeom

    attr = geom.GetWidthsAttr()
    values = attr.Get(time) if attr.HasAuthoredValue() else None
    interp = geom.GetWidthsInterpolation()
    if values is None or len(values) == 0:
        pv = UsdGeom.PrimvarsAPI(geom.GetPrim()).GetPrimvar("widths")
        if not pv or not pv.HasAuthoredValue():
            return None
        values, interp = pv.ComputeFlattened(time), pv.GetInterpolation()
    w = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(w) == 0:
        return None  # authored empty: no widths
    total, n = int(counts.sum()), len(counts)
    if len(w) == 1 or interp == UsdGeom.Tokens.constant:
        return np.full(total, w[0])
    if len(w) == n and interp == UsdGeom.Tokens.uniform:
        return np.repeat(w, counts)
    if len(w) == total:
        return w
    # varying (one per segment end) or a count that fits nothing exactly: spread each curve's share evenly
    per = np.array_split(w, n) if len(w) >= n else None
    if per is None:
        raise UsdFileError(f"{where}: {len(w)} widths for {n} curves of {total} vertices")
    return np.concatenate([np.interp(np.linspace(0, 1, c), np.linspace(0, 1, len(p)), p) if len(p) > 1
                           else np.full(c, p[0]) for p, c in zip(per, counts, strict=True)])


def _root_uv(prim, counts: np.ndarray, time) -> np.ndarray | None:
    """(C, 2) root texture coordinates from the first UV primvar the prim has, or None."""
    from pxr import UsdGeom

    api = UsdGeom.PrimvarsAPI(prim)
    for name in _UV_PRIMVARS:
        pv = api.GetPrimvar(name)
        if not pv or not pv.HasAuthoredValue():
            continue
        values = pv.ComputeFlattened(time)
        if values is None:
            continue
        a = np.asarray(values, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] < 2:
            continue
        a = a[:, :2]
        interp = pv.GetInterpolation()
        if len(a) == 1 or interp == UsdGeom.Tokens.constant:
            return np.repeat(a[:1], len(counts), axis=0)
        if len(a) == len(counts):
            return a
        if len(a) == int(counts.sum()):
            return a[np.concatenate([[0], np.cumsum(counts)[:-1]])]
    return None


def _basis_polylines(curves, world: np.ndarray, counts, starts, time, where: str):
    """(polyline, parameter in [0, 1] of each sample along the control points) per curve of a BasisCurves prim."""
    from pxr import UsdGeom

    kind = curves.GetTypeAttr().Get(time) or UsdGeom.Tokens.cubic
    basis = curves.GetBasisAttr().Get(time) or UsdGeom.Tokens.bezier
    wrap = curves.GetWrapAttr().Get(time) or UsdGeom.Tokens.nonperiodic
    if wrap == UsdGeom.Tokens.periodic:
        raise UsdFileError(f"{where}: periodic curves (closed loops) are not hair strands")
    out = []
    for s, c in zip(starts, counts, strict=True):
        ctrl = world[s:s + c]
        if kind == UsdGeom.Tokens.linear or c < 2:
            out.append((ctrl, np.linspace(0.0, 1.0, c)))
        elif basis == UsdGeom.Tokens.bezier:
            out.append(bezier_polyline(ctrl, where))
        elif basis in (UsdGeom.Tokens.bspline, UsdGeom.Tokens.catmullRom):
            out.append(uniform_cubic_polyline(ctrl, str(basis), pinned=wrap == UsdGeom.Tokens.pinned))
        else:
            raise UsdFileError(f"{where}: curve basis {basis!r} is not supported")
    return out


def bezier_polyline(ctrl: np.ndarray, where: str = "curve", samples: int = SAMPLES_PER_SEGMENT):
    """A cubic Bezier spline of ``3 k + 1`` control points (segments share their ends) sampled ``samples`` times
    per segment; returns (points, parameter in [0, 1] along the control points)."""
    n = len(ctrl)
    if n < 4 or (n - 1) % 3:
        raise UsdFileError(f"{where}: a cubic bezier curve needs 3 k + 1 >= 4 vertices, got {n}")
    t = np.linspace(0.0, 1.0, samples + 1)[:-1]
    b = np.stack([(1 - t) ** 3, 3 * t * (1 - t) ** 2, 3 * t ** 2 * (1 - t), t ** 3], axis=1)  # Bernstein
    segs = [b @ ctrl[3 * i:3 * i + 4] for i in range((n - 1) // 3)]
    pts = np.concatenate(segs + [ctrl[-1:]])
    return pts, np.linspace(0.0, 1.0, len(pts))


_UNIFORM_CUBIC = {
    # Rows: the weights of P[i-1], P[i], P[i+1], P[i+2] for 1, t, t^2, t^3 of segment i.
    "bspline": np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], dtype=np.float64) / 6.0,
    "catmullRom": np.array([[0, 2, 0, 0], [-1, 0, 1, 0], [2, -5, 4, -1], [-1, 3, -3, 1]], dtype=np.float64) / 2.0,
}


def uniform_cubic_polyline(ctrl: np.ndarray, basis: str, *, pinned: bool, samples: int = SAMPLES_PER_SEGMENT):
    """A uniform cubic B-spline or Catmull-Rom curve (``vstep`` 1) sampled ``samples`` times per segment; with
    ``pinned``, USD's phantom points ``P[-1] = 2 P[0] - P[1]``, ``P[n] = 2 P[n-1] - P[n-2]`` make it start and end
    at the end points. Returns (points, parameter in [0, 1] along the control points)."""
    p = np.asarray(ctrl, dtype=np.float64)
    if pinned:
        p = np.concatenate([2 * p[:1] - p[1:2], p, 2 * p[-1:] - p[-2:-1]])
    if len(p) < 4:
        return np.asarray(ctrl, dtype=np.float64), np.linspace(0.0, 1.0, len(ctrl))
    m = _UNIFORM_CUBIC[basis]
    t = np.linspace(0.0, 1.0, samples + 1)
    powers = np.stack([np.ones_like(t), t, t ** 2, t ** 3], axis=1) @ m  # (samples+1, 4)
    segs = [powers[:-1] @ p[i - 1:i + 3] for i in range(1, len(p) - 2)]
    last = powers[-1:] @ p[len(p) - 4:]
    pts = np.concatenate(segs + [last])
    return pts, np.linspace(0.0, 1.0, len(pts))


def _nurbs_polylines(curves, world: np.ndarray, counts, starts, time, where: str):
    """(polyline, parameter in [0, 1]) per curve of a NurbsCurves prim, evaluated with its knots and order."""
    from scipy.interpolate import BSpline

    order = np.asarray(curves.GetOrderAttr().Get(time) or [], dtype=np.int64)
    knots = np.asarray(curves.GetKnotsAttr().Get(time) or [], dtype=np.float64)
    weights = curves.GetPointWeightsAttr().Get(time)
    weights = None if weights is None or len(weights) == 0 else np.asarray(weights, dtype=np.float64)
    if len(order) != len(counts):
        raise UsdFileError(f"{where}: {len(order)} orders for {len(counts)} curves")
    if len(knots) != int((counts + order).sum()):
        raise UsdFileError(f"{where}: {len(knots)} knots; the curves need sum(vertices + order) = "
                           f"{int((counts + order).sum())}")
    if weights is not None and len(weights) != len(world):
        raise UsdFileError(f"{where}: {len(weights)} pointWeights for {len(world)} points")
    out = []
    k0 = 0
    for s, c, o in zip(starts, counts, order, strict=True):
        t = knots[k0:k0 + c + o]
        k0 += c + o
        k = int(o) - 1
        if k < 1:
            raise UsdFileError(f"{where}: a NURBS curve's order must be 2 or more, got {o}")
        if c < o:
            raise UsdFileError(f"{where}: a NURBS curve of order {o} needs at least {o} vertices, got {c}")
        ctrl = world[s:s + c]
        spans = max(1, int(np.count_nonzero(np.diff(np.unique(t[k:c + 1])) > 0)))
        u = np.linspace(t[k], t[c], spans * SAMPLES_PER_SEGMENT + 1)
        try:
            if weights is None:
                pts = BSpline(t, ctrl, k)(u)
            else:
                w = weights[s:s + c]
                h = BSpline(t, np.column_stack([ctrl * w[:, None], w]), k)(u)
                pts = h[:, :3] / h[:, 3:]
        except ValueError as e:  # scipy's own check of the knots, which names neither file nor curve
            raise UsdFileError(f"{where}: NURBS curve {len(out)}: {e}") from None
        out.append((pts, (u - t[k]) / (t[c] - t[k])))
    return out
