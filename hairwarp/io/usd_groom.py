"""Static grooms in USD: one linear BasisCurves prim written, every BasisCurves prim of a stage read back as
polylines in metres, Z up (see :mod:`hairwarp.io.usd_common` for the layout and the conversions)."""

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
)

__all__ = ["read_curves", "write_curves"]


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
