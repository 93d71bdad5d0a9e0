"""Grooms: guide strands as numpy polylines; generate, import, resample.

A :class:`Groom` holds the guide strands the simulator starts from, on the host, in float64:
metres, right-handed, **Z up**, each strand root first. Everything here is numpy only; the
simulator resamples a groom with :meth:`Groom.resample` when it builds its model.

Sources:

- :func:`scalp_groom` generates strands on an ellipsoid head. The head's face looks toward
  **-y** (so +y is the back of the head and +x its left side); this matches a Y-up asset facing
  +z after the Y-up to Z-up rotation below.
- :meth:`Groom.load` picks a reader by suffix: AMD TressFX ``.tfx`` (:mod:`hairwarp.io.tfx`), Cem Yuksel's
  ``.hair`` (:mod:`hairwarp.io.cem_hair`, which also writes them) and USD (:mod:`hairwarp.io.usd_groom`). They are
  imported when a file is read, so this module holds no file format. ``read_tfx``, ``read_hair`` and
  ``write_hair`` are still reachable from here and from ``hairwarp``.

Y up to Z up: ``(x, y, z)_Yup -> (x, -z, y)_Zup``, a rotation of +90 degrees about x
(:data:`Y_UP_TO_Z_UP`). It keeps handedness, so nothing is mirrored.

Root parametrisation (``root_uv``) of imported grooms: an azimuthal equidistant projection of the
roots' directions seen from a centre inside the head (see :meth:`Groom.with_projected_roots`).
Generated grooms use the same form on their own (polar, azimuth) grid. Either way ``root_uv`` is a
seamless 2-D chart in radians, good for a Delaunay triangulation of the roots.
"""

from __future__ import annotations

import importlib
import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = [
    "Y_UP_TO_Z_UP",
    "Groom",
    "GroomError",
    "read_hair",  # noqa: F822 - lazy, see __getattr__
    "read_tfx",  # noqa: F822
    "scalp_groom",
    "write_hair",  # noqa: F822
]

Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Rotation of +90 degrees about x taking Y-up coordinates to Z-up: (x, y, z) -> (x, -z, y)."""

_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
_SUPPORTED_SUFFIXES = (".tfx", ".hair") + _USD_SUFFIXES


_FORMAT_NAMES = {"read_tfx": "hairwarp.io.tfx", "read_hair": "hairwarp.io.cem_hair",
                 "write_hair": "hairwarp.io.cem_hair"}


def __getattr__(name):
    """The format readers that used to live here, imported from :mod:`hairwarp.io` on first use."""
    module = _FORMAT_NAMES.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


class GroomError(ValueError):
    """A groom that cannot be read, built or used; the message names the file or generator and the strand."""


def _up_matrix(up_axis: str, source: str) -> np.ndarray | None:
    """Rotation taking ``up_axis`` coordinates to Z up, or None when they already are."""
    axis = str(up_axis).lower()
    if axis == "z":
        return None
    if axis == "y":
        return Y_UP_TO_Z_UP
    raise GroomError(f"{source}: up_axis must be 'y' or 'z', got {up_axis!r}")


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise GroomError(f"{path}: no such groom file") from None
    except OSError as exc:
        raise GroomError(f"{path}: cannot read ({exc.strerror or exc})") from None


def _unit_rows(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``v`` scaled to unit length, and the row norms (zero rows stay zero)."""
    norm = np.linalg.norm(v, axis=-1)
    safe = np.where(norm > 0.0, norm, 1.0)
    return v / safe[..., None], norm


@dataclass(eq=False)
class Groom:
    """Guide strands as float64 polylines, root first, metres, Z up.

    Build one with :meth:`from_polylines` (validates), :meth:`load`, or a generator such as
    :func:`scalp_groom`; methods return new grooms and never modify this one.

    Attributes:
        strands: one float64 array of shape (n_i, 3) per strand, vertex 0 = root [m].
        root_uv: (G, 2) 2-D scalp parametrisation of the roots [rad], or None.
        root_normal: (G, 3) unit outward scalp normal at each root, or None when unknown.
        grid_shape: (rows, cols) when the roots lie on a generator grid, strand = r * cols + c; else None.
        source: the file path or generator name, used in messages.
        dropped: indices, among the polylines read, of the strands dropped for being shorter than ``min_length``.
        min_length: the arc length below which strands were dropped [m].
        widths: per-vertex diameters [m], one float64 array (n_i,) per strand, or None (the scene's widths
            are used); read from USD grooms and written to the cache.
        surface_uv: (G, 2) texture coordinates of the roots on the scalp's UV map, as the file gives them (USD
            ``primvars:st``, Unreal's ``groom_root_uv``, Blender's ``surface_uv_coordinate``), or None. Unlike
            ``root_uv`` it may have seams, so only the cache uses it.
    """

    strands: list[np.ndarray]
    root_uv: np.ndarray | None = None
    root_normal: np.ndarray | None = None
    grid_shape: tuple[int, int] | None = None
    source: str = "polylines"
    dropped: tuple[int, ...] = ()
    min_length: float = 0.0
    widths: list[np.ndarray] | None = None
    surface_uv: np.ndarray | None = None

    def __repr__(self) -> str:
        # a summary: the dataclass's own repr printed every vertex (340,000 characters for 200 strands)
        points = sum(len(s) for s in self.strands)
        return (f"Groom({len(self.strands)} strands, {points} points, source={self.source!r}"
                + (f", grid {self.grid_shape[0]} x {self.grid_shape[1]}" if self.grid_shape else "")
                + (f", {len(self.dropped)} dropped" if self.dropped else "") + ")")

    @classmethod
    def from_polylines(
        cls,
        polylines,
        *,
        min_length: float = 1e-3,
        source: str = "polylines",
        root_uv=None,
        root_normal=None,
        grid_shape: tuple[int, int] | None = None,
        widths=None,
        surface_uv=None,
    ) -> Groom:
        """Validates polylines and makes a groom of them.

        Strands shorter than ``min_length`` (arc length) are dropped with one warning that counts
        them; the matching rows of ``root_uv`` and ``root_normal`` go with them, and ``grid_shape``
        becomes None when anything is dropped.

        Args:
            polylines: a sequence of (n_i, 3) arrays (or one (G, n, 3) array), root first [m].
            min_length: strands with a shorter arc length are dropped [m].
            source: the file path or generator name, used in messages and warnings.
            root_uv: optional (G, 2) root parametrisation.
            root_normal: optional (G, 3) outward root normals; normalised here.
            grid_shape: optional (rows, cols) with rows * cols == G.
            widths: optional per-vertex diameters [m], one sequence per strand (same lengths as the strands).
            surface_uv: optional (G, 2) texture coordinates of the roots.

        Returns:
            The groom, strands as float64 copies.

        Raises:
            GroomError: a strand that is not an (n >= 2, 3) array of finite numbers (named by index),
                bad ``root_uv`` / ``root_normal`` / ``grid_shape``, or no strand left.
        """
        if isinstance(polylines, (str, bytes)) or not hasattr(polylines, "__iter__"):
            raise GroomError(f"{source}: polylines must be a sequence of (n, 3) arrays, got {type(polylines).__name__}")
        if not (math.isfinite(min_length) and min_length >= 0.0):
            raise GroomError(f"{source}: min_length must be a finite number >= 0, got {min_length!r}")
        strands = []
        for index, line in enumerate(polylines):
            try:
                a = np.array(line, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise GroomError(f"{source}: strand {index} is not a numeric array ({exc})") from None
            if a.ndim != 2 or a.shape[1] != 3:
                raise GroomError(f"{source}: strand {index} must have shape (n >= 2, 3), got {a.shape}")
            if a.shape[0] < 2:
                raise GroomError(f"{source}: strand {index} has {a.shape[0]} point{'s' * (a.shape[0] != 1)}; "
                                 f"a strand needs at least 2")
            bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
            if bad.size:
                more = f"; {bad.size} such vertices in it" if bad.size > 1 else ""
                raise GroomError(f"{source}: strand {index} vertex {int(bad[0])} is not finite "
                                 f"({', '.join(f'{x:g}' for x in a[bad[0]])}){more}")
            strands.append(a)
        count = len(strands)
        if count == 0:
            raise GroomError(f"{source}: no strands")
        uv = _optional_rows(root_uv, count, 2, "root_uv", source)
        tex = _optional_rows(surface_uv, count, 2, "surface_uv", source)
        if widths is not None:
            widths = [np.asarray(w, dtype=np.float64).reshape(-1) for w in widths]
            if len(widths) != count:
                raise GroomError(f"{source}: widths has {len(widths)} strands, the groom {count}")
            for index, (w, a) in enumerate(zip(widths, strands, strict=True)):
                if w.shape != (len(a),) or not np.all(np.isfinite(w)) or np.any(w < 0.0):
                    raise GroomError(f"{source}: widths of strand {index} must be {len(a)} finite numbers >= 0")
        normal = _optional_rows(root_normal, count, 3, "root_normal", source)
        if normal is not None:
            normal, norm = _unit_rows(normal)
            if (norm == 0.0).any():
                raise GroomError(f"{source}: root_normal of strand {int(np.argmin(norm))} is zero")
        if grid_shape is not None:
            rows, cols = (int(x) for x in grid_shape)
            if rows < 1 or cols < 1 or rows * cols != count:
                raise GroomError(f"{source}: grid_shape {tuple(grid_shape)} does not hold {count} strands")
            grid_shape = (rows, cols)

        lengths = np.array([_arc_length(a) for a in strands])
        keep = lengths >= min_length
        dropped = count - int(keep.sum())
        if dropped == count:
            raise GroomError(f"{source}: all {count} strands are shorter than min_length = {min_length:g} m")
        if dropped:
            warnings.warn(
                f"{source}: dropped {dropped} of {count} strands shorter than {min_length:g} m "
                f"({_index_list(np.flatnonzero(~keep))})",
                UserWarning,
                stacklevel=2,
            )
            strands = [a for a, k in zip(strands, keep, strict=True) if k]
            uv = None if uv is None else uv[keep]
            normal = None if normal is None else normal[keep]
            tex = None if tex is None else tex[keep]
            widths = None if widths is None else [w for w, k in zip(widths, keep, strict=True) if k]
            grid_shape = None
        return cls(strands=strands, root_uv=uv, root_normal=normal, grid_shape=grid_shape, source=str(source),
                   dropped=tuple(int(i) for i in np.flatnonzero(~keep)), min_length=float(min_length),
                   widths=widths, surface_uv=tex)

    @classmethod
    def load(cls, path, *, min_length: float = 1e-3, up_axis: str | None = None, purpose: str = "auto") -> Groom:
        """Reads a groom file, choosing the reader by suffix.

        Args:
            path: a ``.tfx``, ``.hair`` or ``.usd`` / ``.usda`` / ``.usdc`` / ``.usdz`` file.
            min_length: strands with a shorter arc length are dropped with a warning [m].
            up_axis: ``"y"`` or ``"z"``: the up axis the file's coordinates use, for formats that do not
                record it (default: Y for ``.tfx``, Z for ``.hair``). USD stages carry their own.
            purpose: USD stages: which curves to read by their UsdGeom purpose: "guide", "render" (every
                curve not of purpose guide), "all", or "auto" (the guides when the stage has both, else all).

        Returns:
            The groom in metres, Z up, with ``root_uv`` and ``root_normal`` estimated by
            :meth:`with_projected_roots`.

        Raises:
            GroomError: missing file, unknown suffix, or a file that cannot be read.
        """
        p = Path(path)
        suffix = p.suffix.lower()
        if suffix not in _SUPPORTED_SUFFIXES:
            raise GroomError(f"{p}: unknown groom suffix {p.suffix!r}; supported: {', '.join(_SUPPORTED_SUFFIXES)}")
        if not p.is_file():
            raise GroomError(f"{p}: no such groom file")
        # The readers are imported here: the domain type holds no file format (and hairwarp.io's USD modules pull
        # in pxr, which step-API users need not load).
        if suffix == ".tfx":
            from hairwarp.io.tfx import read_tfx

            return read_tfx(p, min_length=min_length, up_axis=up_axis or "y")
        if suffix == ".hair":
            from hairwarp.io.cem_hair import read_hair

            return read_hair(p, min_length=min_length, up_axis=up_axis or "z")
        if up_axis is not None:
            raise GroomError(f"{p}: up_axis applies to .tfx and .hair files; USD stages record their own upAxis")
        # Imported here: hairwarp.io pulls in pxr, which step-API users need not load.
        data = importlib.import_module("hairwarp.io.usd_groom").read_groom(p, purpose=purpose)
        return cls.from_polylines(data["curves"], min_length=min_length, source=str(p), widths=data["widths"],
                                  surface_uv=data["uv"]).with_projected_roots()

    @property
    def strand_count(self) -> int:
        """Number of strands G."""
        return len(self.strands)

    def lengths(self) -> np.ndarray:
        """Arc length of each strand [m], shape (G,)."""
        return np.array([_arc_length(a) for a in self.strands])

    def roots(self) -> np.ndarray:
        """Root positions [m], shape (G, 3)."""
        return np.array([a[0] for a in self.strands])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of all vertices: (min (3,), max (3,)) [m]."""
        lo = np.min([a.min(axis=0) for a in self.strands], axis=0)
        hi = np.max([a.max(axis=0) for a in self.strands], axis=0)
        return lo, hi

    def resample(self, segments: int) -> np.ndarray:
        """Resamples every strand to ``segments`` equal arc-length pieces.

        Vertex j of a strand lies at arc length ``j * L / segments`` along the original polyline
        (linear interpolation), so root and tip are kept exactly and a straight strand gets equal
        segments; on a bent polyline each chord is at most ``L / segments``.

        Args:
            segments: S >= 1.

        Returns:
            float64 array of shape (G, S + 1, 3) [m].
        """
        s = int(segments)
        if s != segments or s < 1:
            raise GroomError(f"{self.source}: segments must be an integer >= 1, got {segments!r}")
        out = np.empty((self.strand_count, s + 1, 3))
        for g, a in enumerate(self.strands):
            seg = np.linalg.norm(np.diff(a, axis=0), axis=1)
            keep = np.concatenate(([True], seg > 0.0))
            pts = a[keep]
            cum = np.concatenate(([0.0], np.cumsum(seg[seg > 0.0])))
            target = np.linspace(0.0, cum[-1], s + 1)
            for axis in range(3):
                out[g, :, axis] = np.interp(target, cum, pts[:, axis])
            out[g, 0] = a[0]
            out[g, -1] = a[-1]
        return out

    def resampled_widths(self, segments: int) -> np.ndarray | None:
        """The per-vertex ``widths`` at the vertices of :meth:`resample` (linear in arc length), shape
        (G, S + 1) [m], or None when the groom has none."""
        if self.widths is None:
            return None
        s = int(segments)
        out = np.empty((self.strand_count, s + 1))
        for g, (a, w) in enumerate(zip(self.strands, self.widths, strict=True)):
            cum = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(a, axis=0), axis=1))))
            out[g] = np.interp(np.linspace(0.0, cum[-1], s + 1), cum, w)
        return out

    def transformed(self, matrix) -> Groom:
        """Applies a 3x3 linear or 4x4 affine transform (numpy, column vectors).

        Root normals are mapped by the inverse transpose and renormalised, so they stay outward
        under any invertible transform; ``root_uv`` and ``grid_shape`` are kept.

        Raises:
            GroomError: wrong shape, non-finite, singular, or a 4x4 whose last row is not (0, 0, 0, 1).
        """
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape not in ((3, 3), (4, 4)) or not np.isfinite(m).all():
            raise GroomError(f"{self.source}: transform must be a finite 3x3 or 4x4 matrix, got shape {m.shape}")
        if m.shape == (4, 4):
            if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), rtol=0.0, atol=1e-12):
                raise GroomError(f"{self.source}: 4x4 transform must be affine (last row 0 0 0 1), got {m[3]}")
            linear, offset = m[:3, :3], m[:3, 3]
        else:
            linear, offset = m, np.zeros(3)
        if abs(np.linalg.det(linear)) <= 1e-300:
            raise GroomError(f"{self.source}: transform is singular")
        strands = [a @ linear.T + offset for a in self.strands]
        normal = None
        if self.root_normal is not None:
            normal, _ = _unit_rows(self.root_normal @ np.linalg.inv(linear))
        widths = self.widths
        if widths is not None:  # a width scales with the transform's mean length factor
            factor = abs(np.linalg.det(linear)) ** (1.0 / 3.0)
            widths = [w * factor for w in widths]
        return replace(self, strands=strands, root_normal=normal, widths=widths)

    def without_short(self, min_length: float) -> Groom:
        """This groom less its strands shorter than ``min_length`` [m] (arc length), with the warning
        :meth:`from_polylines` gives; for a groom whose units were set after it was read."""
        return Groom.from_polylines(self.strands, min_length=min_length, source=self.source, root_uv=self.root_uv,
                                    root_normal=self.root_normal, grid_shape=self.grid_shape, widths=self.widths,
                                    surface_uv=self.surface_uv)

    def subset(self, indices) -> Groom:
        """The strands at ``indices`` (integer indices or a boolean mask of length G), in that order.

        ``grid_shape`` is kept only when the subset is the whole groom in order.
        """
        idx = np.asarray(indices)
        if idx.dtype == bool:
            if idx.shape != (self.strand_count,):
                raise GroomError(f"{self.source}: boolean subset mask must have shape ({self.strand_count},)")
            idx = np.flatnonzero(idx)
        idx = idx.astype(np.int64, casting="same_kind").reshape(-1)
        if idx.size == 0:
            raise GroomError(f"{self.source}: empty subset")
        bad = (idx < -self.strand_count) | (idx >= self.strand_count)
        if bad.any():
            raise GroomError(f"{self.source}: subset index {int(idx[bad][0])} out of range for {self.strand_count}")
        idx = idx % self.strand_count
        whole = idx.size == self.strand_count and bool((idx == np.arange(self.strand_count)).all())
        return Groom(
            strands=[self.strands[i].copy() for i in idx],
            root_uv=None if self.root_uv is None else self.root_uv[idx],
            root_normal=None if self.root_normal is None else self.root_normal[idx],
            grid_shape=self.grid_shape if whole else None,
            source=self.source,
            widths=None if self.widths is None else [self.widths[i].copy() for i in idx],
            surface_uv=None if self.surface_uv is None else self.surface_uv[idx],
        )

    def with_projected_roots(self, *, overwrite: bool = False) -> Groom:
        """Estimates ``root_uv`` and ``root_normal`` from the roots alone (for imported grooms).

        Centre: the least-squares sphere through the roots; when the fit is degenerate (fewer than
        four roots, roots on a plane or line, a radius over ten times the roots' extent) or puts the
        centre on the wrong side (most strands would leave their root inward), the centre of the
        roots' bounding box instead. Normal: ``(root - centre)`` normalised (the first segment's
        direction for a root at the centre). Chart: azimuthal equidistant projection about the mean
        normal ``e0``: ``root_uv = angle(n, e0) * (cos a, sin a)`` [rad], the azimuth ``a`` measured in
        the plane of ``e1 = e2 x e0`` and ``e2`` = +y made orthogonal to ``e0``. It has no seam, and only
        the direction opposite ``e0`` is singular. For the TressFX Ratboy mohawk the sphere normals
        are within 17 degrees (median) of the body mesh's normals.

        Args:
            overwrite: replace ``root_uv`` / ``root_normal`` already present (default: keep them).

        Returns:
            A groom with both filled in.
        """
        if self.root_uv is not None and self.root_normal is not None and not overwrite:
            return self
        roots = self.roots()
        first = np.array([_first_direction(a) for a in self.strands])
        uv, normal = _projected_roots(roots, first)
        return replace(
            self,
            root_uv=uv if overwrite or self.root_uv is None else self.root_uv,
            root_normal=normal if overwrite or self.root_normal is None else self.root_normal,
        )


def _optional_rows(value, count: int, width: int, name: str, source: str) -> np.ndarray | None:
    """``value`` as a finite float64 (count, width) array, or None."""
    if value is None:
        return None
    a = np.array(value, dtype=np.float64)
    if a.shape != (count, width):
        raise GroomError(f"{source}: {name} must have shape ({count}, {width}), got {a.shape}")
    if not np.isfinite(a).all():
        raise GroomError(f"{source}: {name} has non-finite values")
    return a


def _index_list(indices, limit: int = 8) -> str:
    """``strand 3`` or ``strands 0, 4, 9`` (the first ``limit``, then how many more)."""
    idx = [int(i) for i in indices]
    text = ", ".join(str(i) for i in idx[:limit]) + (f" and {len(idx) - limit} more" if len(idx) > limit else "")
    return f"strand{'s' * (len(idx) != 1)} {text}"


def _arc_length(a: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(a, axis=0), axis=1).sum())


def _first_direction(a: np.ndarray) -> np.ndarray:
    """Unit direction from the root to the first vertex apart from it (zero for a point-like strand)."""
    d = a[1:] - a[0]
    norm = np.linalg.norm(d, axis=1)
    nz = np.flatnonzero(norm > 0.0)
    return d[nz[0]] / norm[nz[0]] if nz.size else np.zeros(3)


def _projected_roots(roots: np.ndarray, first_dir: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root chart and normals seen from a centre inside the head; see ``Groom.with_projected_roots``."""
    lo, hi = roots.min(axis=0), roots.max(axis=0)
    extent = float(np.linalg.norm(hi - lo))
    candidates = []
    if len(roots) >= 4 and extent > 0.0:
        a = np.column_stack((2.0 * roots, np.ones(len(roots))))
        sol, _, rank, sv = np.linalg.lstsq(a, (roots * roots).sum(axis=1), rcond=None)
        centre = sol[:3]
        r2 = sol[3] + centre @ centre
        if rank == 4 and sv[-1] > 1e-9 * sv[0] and r2 > 0.0 and math.sqrt(r2) < 10.0 * extent:
            candidates.append(centre)
    candidates.append(0.5 * (lo + hi))
    for i, centre in enumerate(candidates):
        normal, norm = _unit_rows(roots - centre)
        normal[norm <= 1e-12 * max(extent, 1e-300)] = first_dir[norm <= 1e-12 * max(extent, 1e-300)]
        outward = np.median((normal * first_dir).sum(axis=1)) > 0.0
        if outward or i == len(candidates) - 1:
            break
    e0, n0 = _unit_rows(normal.mean(axis=0))
    if n0 < 1e-6:
        e0 = np.array([0.0, 0.0, 1.0])
    e2 = np.array([0.0, 1.0, 0.0]) - e0[1] * e0
    if np.linalg.norm(e2) < 1e-6:
        e2 = np.array([0.0, 0.0, 1.0]) - e0[2] * e0
    e2 /= np.linalg.norm(e2)
    e1 = np.cross(e2, e0)
    t = np.column_stack((normal @ e1, normal @ e2))
    sin_angle = np.linalg.norm(t, axis=1)
    angle = np.arctan2(sin_angle, normal @ e0)
    uv = t * (angle / np.where(sin_angle > 0.0, sin_angle, 1.0))[:, None]
    return uv, normal


# --------------------------------------------------------------------------------------------
# Generator


def scalp_groom(
    count: int = 200,
    length: float = 0.3,
    *,
    points: int = 32,
    curl: float = 0.0,
    curl_period: float = 0.05,
    scalp_center=(0.0, 0.0, 1.6),
    scalp_radii=(0.085, 0.1, 0.11),
    cap_angle_deg: float = 110.0,
    front_cutoff_deg: float = 55.0,
    margin: float = 0.004,
    seed: int = 0,
) -> Groom:
    """Generates a combed-back head of hair on an ellipsoid head (face toward -y).

    Roots: an ellipsoid ``c + r * (sin t sin a, -sin t cos a, cos t)`` (semi-axes ``scalp_radii``
    along x, y, z) sampled on a rows x cols grid in polar angle ``t`` (from the crown) and azimuth
    ``a`` (from the face, through +x). The polar range at azimuth ``a`` is
    ``t_max(a) = front + (cap - front) sin^2(a / 2)``: ``cap_angle_deg`` at the back,
    ``front_cutoff_deg`` at the forehead hairline, so the face has no roots. Rows sit at
    ``t = (r + 1/2) / rows * t_max``, columns at ``a = 2 pi (c + 1/2) / cols`` (the azimuth seam is a
    centre parting at the front), each jittered by up to 0.3 cell. ``root_uv = t (sin a, -cos a)``,
    the grid seen from above (u along +x, v along +y) [rad]; strand = r * cols + c.

    Strands: a polyline of ``points`` vertices and equal steps; the step direction leaves along the
    scalp normal for ``max(margin, 4 mm)``, turns (radius 1.2 cm) toward the comb direction (the
    scalp tangent of (0, 1, -1/2), pointing back and down), then (radius 4 cm) toward gravity
    leaning slightly back, (0, 0.1, -1) normalised. Every vertex after the root is kept at least
    ``margin`` from the ellipsoid by turning the step toward the outward normal (bisection), so the
    strand slides over the head and keeps its length. ``curl`` adds a helix of that radius whose
    turn takes ``curl_period`` of arc length, ramped in over half a period. Lengths are
    ``length * (1 +- 5 %)`` at random.

    A vertex at arc length ``s < margin`` from its root can only be ``s`` clear of the head; it lies on
    the normal at that distance (this happens when a step is shorter than ``margin``).

    Args:
        count: guide strands wanted; the grid holds rows * cols within about 5 % of it.
        length: mean strand length [m].
        points: vertices per strand (>= 2).
        curl: helix radius [m]; 0 for straight hair. Needs ``2 pi curl < curl_period``.
        curl_period: arc length of one helix turn [m]; about 5 points per period show it.
        scalp_center: ellipsoid centre [m].
        scalp_radii: ellipsoid semi-axes along x, y, z [m].
        cap_angle_deg: largest polar angle of a root, at the back of the head [deg].
        front_cutoff_deg: largest polar angle at the front (the forehead hairline) [deg].
        margin: clearance of every non-root vertex from the ellipsoid [m].
        seed: random seed of the jitter; the same seed gives the same groom.

    Returns:
        The groom, with ``root_uv``, ``root_normal`` and ``grid_shape`` set; source "scalp_groom".
    """
    src = "scalp_groom"
    centre = np.array(scalp_center, dtype=np.float64).reshape(-1)
    radii = np.array(scalp_radii, dtype=np.float64).reshape(-1)
    _check(isinstance(count, (int, np.integer)) and count >= 1, src, f"count must be an integer >= 1, got {count!r}")
    _check(
        isinstance(points, (int, np.integer)) and points >= 2, src, f"points must be an integer >= 2, got {points!r}"
    )
    _check(math.isfinite(length) and length > 0.0, src, f"length must be > 0, got {length!r}")
    _check(centre.shape == (3,) and np.isfinite(centre).all(), src, "scalp_center must be 3 finite numbers")
    _check(radii.shape == (3,) and np.isfinite(radii).all() and (radii > 0).all(), src, "scalp_radii must be 3 > 0")
    _check(0.0 < front_cutoff_deg <= cap_angle_deg < 180.0, src, "need 0 < front_cutoff_deg <= cap_angle_deg < 180")
    _check(math.isfinite(margin) and margin >= 0.0, src, f"margin must be >= 0, got {margin!r}")
    _check(math.isfinite(curl_period) and curl_period > 0.0, src, "curl_period must be > 0")
    _check(
        math.isfinite(curl) and 0.0 <= 2.0 * math.pi * curl < curl_period,
        src,
        f"curl must be >= 0 and 2 pi curl < curl_period ({curl!r}, {curl_period!r})",
    )
    rng = np.random.default_rng(seed)
    front = math.radians(front_cutoff_deg)
    cap = math.radians(cap_angle_deg)

    rows, cols = _grid_shape(int(count), 0.5 * (front + cap))
    r_idx, c_idx = np.divmod(np.arange(rows * cols), cols)
    azimuth = 2.0 * np.pi * (c_idx + 0.5 + rng.uniform(-0.3, 0.3, rows * cols)) / cols
    fraction = (r_idx + 0.5 + rng.uniform(-0.3, 0.3, rows * cols)) / rows
    polar = fraction * (front + (cap - front) * np.sin(0.5 * azimuth) ** 2)
    unit = np.column_stack((np.sin(polar) * np.sin(azimuth), -np.sin(polar) * np.cos(azimuth), np.cos(polar)))
    roots = centre + radii * unit
    normal, _ = _unit_rows(unit / radii)
    root_uv = polar[:, None] * np.column_stack((np.sin(azimuth), -np.cos(azimuth)))
    lengths = length * (1.0 + rng.uniform(-0.05, 0.05, rows * cols))

    verts = _grow_strands(roots, normal, lengths, points, curl, curl_period, centre, radii, margin)
    return Groom.from_polylines(
        list(verts),
        min_length=0.0,
        source=src,
        root_uv=root_uv,
        root_normal=normal,
        grid_shape=(rows, cols),
    )


def _check(ok: bool, source: str, message: str) -> None:
    if not ok:
        raise GroomError(f"{source}: {message}")


def _grid_shape(count: int, mean_polar: float) -> tuple[int, int]:
    """(rows, cols) with rows * cols near ``count`` and cells about square at mid-cap."""
    aspect = 2.0 * math.pi * math.sin(0.5 * mean_polar) / mean_polar  # cols per row for square cells
    best = None
    for rows in range(1, count + 1):
        cols = max(1, round(count / rows))
        error = abs(rows * cols - count) / count
        score = (error > 0.05, abs(math.log(cols / (rows * aspect))) if error <= 0.05 else error)
        if best is None or score < best[0]:
            best = (score, rows, cols)
    return best[1], best[2]


_LIFT = 0.004  # distance a strand leaves along the scalp normal [m]
_COMB_RADIUS = 0.012  # bend radius from the normal to the comb direction [m]
_FALL_RADIUS = 0.04  # bend radius from the comb direction to gravity [m]
_COMB = np.array([0.0, 1.0, -0.5])  # combed back and down, projected on the scalp
_FALL = np.array([0.0, 0.1, -1.0]) / math.hypot(0.1, 1.0)  # gravity, leaning back


def _grow_strands(roots, normal, lengths, points, curl, curl_period, centre, radii, margin) -> np.ndarray:
    """Steps all strands at once from their roots; returns (G, points, 3)."""
    count = len(roots)
    h = lengths / (points - 1)
    comb = _COMB - (normal @ _COMB)[:, None] * normal
    comb_unit, comb_norm = _unit_rows(comb)
    # A normal parallel to the comb direction has no tangent part; comb straight down then.
    fallback, _ = _unit_rows(_FALL - (normal @ _FALL)[:, None] * normal)
    comb_unit[comb_norm < 1e-6] = fallback[comb_norm < 1e-6]
    d = normal.copy()
    e1 = comb_unit.copy()
    e2 = np.cross(d, e1)
    combed = np.zeros(count, dtype=bool)
    lift = max(margin, _LIFT)
    sin_cone = 2.0 * math.pi * curl / curl_period

    verts = np.empty((count, points, 3))
    verts[:, 0] = roots
    p = roots.copy()
    gap_p, out_p = np.zeros(count), normal.copy()
    for k in range(points - 1):
        s = k * h
        turning = s >= lift
        target = np.where(combed[:, None], _FALL, comb_unit)
        radius = np.where(combed, _FALL_RADIUS, _COMB_RADIUS)
        max_angle = np.where(turning, h / radius, 0.0)
        d, e1, e2, reached = _turn_toward(d, e1, e2, target, max_angle)
        combed |= turning & reached
        step = d
        if sin_cone > 0.0:
            ramp = np.clip((s - lift) / (0.5 * curl_period), 0.0, 1.0)
            sb = sin_cone * ramp
            psi = 2.0 * np.pi * (s + 0.5 * h) / curl_period
            step = np.sqrt(1.0 - sb * sb)[:, None] * d + sb[:, None] * (
                np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2
            )
        q = p + h[:, None] * step
        gap_q, _ = _ellipsoid_gap(q, centre, radii)
        # Within margin of the root only the normal direction gets as far out as possible.
        need = np.minimum(margin, gap_p + h)
        bad = gap_q < need
        if bad.any():
            fixed = _clear_step(p[bad], step[bad], out_p[bad], h[bad], centre, radii, need[bad])
            rot = _min_rotation(step[bad], fixed)
            d[bad], e1[bad], e2[bad] = rot(d[bad]), rot(e1[bad]), rot(e2[bad])
            q[bad] = p[bad] + h[bad, None] * fixed
        p = q
        verts[:, k + 1] = p
        gap_p, out_p = _ellipsoid_gap(p, centre, radii)
    return verts


def _turn_toward(d, e1, e2, target, max_angle):
    """Rotates unit ``d`` (and its frame) toward ``target`` by at most ``max_angle``; also says which reached it."""
    cos_a = np.clip((d * target).sum(axis=1), -1.0, 1.0)
    angle = np.arccos(cos_a)
    axis, norm = _unit_rows(np.cross(d, target))
    # Antiparallel target: any axis perpendicular to d turns it; e1 is one.
    axis[norm < 1e-12] = e1[norm < 1e-12]
    turn = np.minimum(angle, max_angle)
    reached = angle <= max_angle + 1e-12
    return _rotate(d, axis, turn), _rotate(e1, axis, turn), _rotate(e2, axis, turn), reached


def _rotate(v, axis, angle):
    """Rodrigues' rotation of the rows of v about unit ``axis`` rows by ``angle``."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(axis, v) * s + axis * ((axis * v).sum(axis=1, keepdims=True) * (1.0 - c))


def _min_rotation(a, b):
    """The smallest rotation taking unit rows ``a`` to unit rows ``b``, as a function of rows."""
    axis, sin_a = _unit_rows(np.cross(a, b))
    cos_a = np.clip((a * b).sum(axis=1), -1.0, 1.0)
    angle = np.arctan2(sin_a, cos_a)
    return lambda v: _rotate(v, axis, angle)


def _clear_step(p, step, outward, h, centre, radii, margin):
    """Unit steps from ``p`` turned toward ``outward`` just enough to end ``margin`` (per row) clear of the ellipsoid.

    Bisection on the blend ``normalize((1 - w) step + w outward)``: w = 0 is inside the margin,
    w = 1 (straight out along the normal) is clear when ``margin <= gap(p) + h``.
    """
    lo = np.zeros(len(p))
    hi = np.ones(len(p))

    def blend(w):
        v = (1.0 - w)[:, None] * step + w[:, None] * outward
        v, norm = _unit_rows(v)
        v[norm < 1e-12] = outward[norm < 1e-12]
        return v

    for _ in range(40):
        mid = 0.5 * (lo + hi)
        gap, _ = _ellipsoid_gap(p + h[:, None] * blend(mid), centre, radii)
        ok = gap >= margin
        hi = np.where(ok, mid, hi)
        lo = np.where(ok, lo, mid)
    return blend(hi)


def _ellipsoid_gap(points, centre, radii):
    """Distance of points outside an axis-aligned ellipsoid, and the outward normal at the closest point.

    Closest point by Newton's method on the Lagrange multiplier (Eberly, "Distance from a point to an
    ellipse, an ellipsoid, or a hyperellipsoid"): ``sum (r_i y_i / (t + r_i^2))^2 = 1``, convex and
    decreasing in t >= 0, started below the root so the iterates rise monotonically. Points inside get
    a negative gap (the implicit value's shortfall times the smallest radius, not a distance).
    """
    y = points - centre
    r2 = radii * radii
    f = ((y / radii) ** 2).sum(axis=1)
    inside = f < 1.0
    t = np.maximum(0.0, radii.min() * np.linalg.norm(y, axis=1) - r2.max())
    t[inside] = 0.0
    for _ in range(100):
        q = radii * y / (t[:, None] + r2)
        value = (q * q).sum(axis=1) - 1.0
        slope = -2.0 * (q * q / (t[:, None] + r2)).sum(axis=1)
        dt = np.where(inside | (value <= 0.0), 0.0, -value / slope)
        t = t + dt
        if (dt <= 1e-15 * (t + r2.max())).all():
            break
    w = y / (t[:, None] + r2)
    normal, norm = _unit_rows(w)
    gap = t * norm
    gap[inside] = -(1.0 - np.sqrt(f[inside])) * radii.min()
    return gap, normal
