"""Pictures of hair caches: contact sheets (PNG) and turntable-free animated GIFs, rendered headless with matplotlib.

The camera is orthographic. A view is a name from :data:`VIEWS` or an ``(azimuth, elevation)`` pair in degrees:
azimuth 0 looks at the face of a head that faces -y (the convention of :func:`hairwarp.groom.scalp_groom`), 90 looks
from +x, 180 from behind; elevation lifts the camera above the xy plane (Z up). Hair is drawn as thin lines shaded
from a dark root to a light tip and darkened with depth; collider meshes as a light grey, Lambert-shaded silhouette.
Visibility is approximated by the painter's algorithm over depth slices shared by hair and meshes, so hair behind
a head is hidden by it and hair in front is drawn over it.

``matplotlib`` and ``PIL`` are imported inside the functions that need them; the Agg backend is used directly,
so no display is ever needed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["VIEWS", "PreviewWriteError", "cache_frames", "preview_cache", "render_frames", "render_grid"]

VIEWS = {
    "front": (0.0, 0.0),
    "three_quarter": (35.0, 12.0),
    "side": (90.0, 0.0),
    "three_quarter_back": (145.0, 12.0),
    "back": (180.0, 0.0),
    "top": (0.0, 90.0),
}
"""Named views: (azimuth, elevation) in degrees."""

BACKGROUND = "#eeedea"
CAPTION_COLOR = "#6b6b6b"
HAIR_RAMP = ((0.20, 0.12, 0.07), (0.50, 0.32, 0.16), (0.84, 0.65, 0.40))
"""Root, middle and tip colour of dense hair (dark brown to honey)."""
GUIDE_RAMP = ((0.55, 0.20, 0.05), (0.90, 0.45, 0.12), (1.00, 0.72, 0.35))
"""Root, middle and tip colour of guide curves (prims whose name contains "guide"), orange like in USD viewports."""
MESH_GREY = 0.86
"""Albedo of collider meshes (light grey)."""
KEY_LIGHT = np.array([-0.45, 0.55, -0.70]) / np.linalg.norm([-0.45, 0.55, -0.70])
"""Direction to the key light in screen axes (right, up, into the screen): upper left, in front of the subject."""
AMBIENT, KEY_WEIGHT = 0.42, 0.38
"""Mesh shade = ambient + key * Lambert + the rest * facing ratio (a soft head light)."""
DEPTH_DARKEN = 0.35
"""Fraction by which the farthest hair is darkened relative to the nearest."""
DEPTH_SLICES = 32
"""Depth layers of the painter's algorithm; hair and mesh triangles in one layer are drawn far to near."""
MAX_POLYLINES = 40000
MAX_CHUNK_SEGMENTS = 6
"""Hair is drawn as polylines of up to 6 segments, each of one colour, so that a panel holds at most about 40,000
of them: 10 colour steps along a strand still read as a smooth ramp. The polylines of one colour in a depth slice are
drawn as one path (``_colour_paths``), since matplotlib's cost is per path (~10 us)."""
COLOUR_STEPS = 24
"""Levels a colour channel takes in the hair of one depth slice: its polylines of a colour are drawn as one path."""
STRAND_JITTER = 0.25
"""Peak-to-peak brightness variation between strands."""
MAX_MESH_FACES = 40000
DPI = 100


class PreviewWriteError(RuntimeError):
    """Writing a picture failed (disk full, I/O error); the message names the path and, for a full disk, the space
    the picture needs and the space free. Nothing is left at the path (see :func:`_save`)."""


def _save(out: Path, encode) -> Path:
    """Write the picture ``encode(stream)`` produces to ``out``, whole or not at all: encoded in memory (so its size
    is known for the message of a full disk), written under a temporary name beside ``out``, flushed and renamed
    over it (``cache_folder.fsync_path``, as the cache's own files). A full disk used to leave a truncated GIF at
    ``out`` and a traceback.

    Raises:
        PreviewWriteError: the folder or the file could not be written; the temporary file is removed.
    """
    import errno
    import io
    import os

    from hairwarp.io.cache_folder import fsync_path

    buffer = io.BytesIO()
    encode(buffer)
    data = buffer.getbuffer()
    tmp = out.with_name(f"{out.stem}.tmp{out.suffix}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(data)
        fsync_path(tmp)  # as the cache's files: flushed, renamed, the folder's entry flushed
        os.replace(tmp, out)
        fsync_path(out.parent)
    except BaseException as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if not isinstance(exc, OSError):
            raise
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            from hairwarp.io.cache_folder import free_bytes
            from hairwarp.io.usd_common import _human_bytes

            raise PreviewWriteError(f"no space left on {out.parent} for the picture {out}: it needs "
                                    f"{_human_bytes(len(data))}, {_human_bytes(free_bytes(out.parent))} are free"
                                    ) from None
        raise PreviewWriteError(f"writing the picture {out} failed: {exc.strerror or exc}") from None
    return out


def _camera(view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screen right, screen up and viewing direction (into the scene) for a named view or (azimuth, elevation)."""
    if isinstance(view, str):
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; choose one of {', '.join(VIEWS)} or give (azimuth, elevation)")
        az, el = VIEWS[view]
    else:
        az, el = (float(v) for v in view)
    az, el = np.radians(az), np.radians(min(max(el, -89.9), 89.9))
    to_camera = np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), np.sin(el)])
    forward = -to_camera
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return right, up, forward


def _ramp(stops, t: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp through equally spaced stops, evaluated at t in [0, 1]; returns (M, 3)."""
    stops = np.asarray(stops, dtype=np.float64)
    x = np.clip(t, 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(x.astype(np.int64), len(stops) - 2)
    f = (x - i)[:, None]
    return stops[i] * (1.0 - f) + stops[i + 1] * f


def _select_curves(curves: dict, max_curves: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Per prim: (name, points, counts) with at most ``max_curves`` curves in all, picked evenly by index.

    The same curves are picked in every frame of a cache (the counts do not change), so animations do not flicker.
    """
    total = sum(len(np.asarray(c)) for _, c in curves.values())
    keep_every = max(1, int(np.ceil(total / max_curves))) if max_curves > 0 else 1
    out = []
    for name, (pts, counts) in curves.items():
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(counts, dtype=np.int64)
        if counts.sum() != len(pts):
            raise ValueError(f"curves {name!r}: {len(pts)} points but the curve vertex counts add up to {counts.sum()}")
        if keep_every > 1:
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
            chosen = np.arange(0, len(counts), keep_every)
            idx = np.concatenate([np.arange(starts[c], starts[c] + counts[c]) for c in chosen])
            pts, counts = pts[idx], counts[chosen]
        out.append((name, pts, counts))
    return out


class _Panel:
    """One frame, projected: hair segments and mesh triangles in screen space with depth and colour."""

    def __init__(self, curves: dict, meshes, cam, max_curves: int):
        right, up, forward = cam
        basis = np.stack([right, up, forward], axis=1)
        segs, seg_depth, seg_rgb = [], [], []
        self.curve_count = 0
        selected = _select_curves(curves, max_curves)
        total_segments = sum(int((c - 1).sum()) for _, _, c in selected)
        chunk = int(np.clip(np.ceil(total_segments / MAX_POLYLINES), 1, MAX_CHUNK_SEGMENTS))
        for name, pts, counts in selected:
            if len(pts) == 0:
                continue
            self.curve_count += len(counts)
            q = pts @ basis
            start, end, t, curve = _chunks(counts, chunk)
            idx = np.minimum(start[:, None] + np.arange(chunk + 1)[None, :], end[:, None])
            segs.append(q[idx, :2])
            seg_depth.append(q[idx, 2].mean(axis=1))
            # A small, fixed brightness variation per strand keeps dense hair from looking like a flat sheet.
            jitter = 1.0 + STRAND_JITTER * (_hash01(curve) - 0.5)
            ramp = GUIDE_RAMP if "guide" in name.lower() else HAIR_RAMP
            seg_rgb.append(np.clip(_ramp(ramp, t) * jitter[:, None], 0.0, 1.0))
        self.segments = np.concatenate(segs) if segs else np.zeros((0, chunk + 1, 2))
        self.seg_depth = np.concatenate(seg_depth) if seg_depth else np.zeros(0)
        self.seg_rgb = np.concatenate(seg_rgb) if seg_rgb else np.zeros((0, 3))

        tris, tri_depth, tri_shade = [], [], []
        for verts, faces in _mesh_list(meshes):
            verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
            faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
            if len(faces) == 0:
                continue
            q = verts @ basis
            corners = q[faces]
            area_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            ok = np.einsum("ij,ij->i", area_normal, area_normal) > 0.0
            faces, corners, area_normal = faces[ok], corners[ok], area_normal[ok]
            closed = _is_closed(faces)
            if closed and _signed_volume(q, faces) < 0.0:
                area_normal = -area_normal  # make a closed mesh's normals point outwards
            # Smooth shading: area-weighted vertex normals, lit per vertex, averaged over each triangle.
            vnormal = np.zeros_like(q)
            for c in range(3):
                np.add.at(vnormal, faces[:, c], area_normal)
            vnormal /= np.maximum(np.linalg.norm(vnormal, axis=1), 1e-30)[:, None]
            lit = vnormal @ KEY_LIGHT
            facing = -vnormal[:, 2]
            if not closed:  # no inside or outside: light both sides alike
                lit, facing = np.abs(lit), np.abs(facing)
            head_light = 1.0 - AMBIENT - KEY_WEIGHT
            vshade = AMBIENT + KEY_WEIGHT * np.clip(lit, 0.0, 1.0) + head_light * np.clip(facing, 0.0, 1.0)
            shade = vshade[faces].mean(axis=1)
            if closed:  # cull the faces turned away from the camera (+z is into the screen)
                front = area_normal[:, 2] < 0.0
                corners, shade = corners[front], shade[front]
            if len(corners) > MAX_MESH_FACES:
                keep = np.linspace(0, len(corners) - 1, MAX_MESH_FACES).astype(np.int64)
                corners, shade = corners[keep], shade[keep]
            tris.append(corners[:, :, :2])
            tri_depth.append(corners[:, :, 2].mean(axis=1))
            tri_shade.append(shade)
        self.triangles = np.concatenate(tris) if tris else np.zeros((0, 3, 2))
        self.tri_depth = np.concatenate(tri_depth) if tri_depth else np.zeros(0)
        self.tri_shade = np.concatenate(tri_shade) if tri_shade else np.zeros(0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Screen-space bounding box of everything in the panel, or None when it is empty."""
        xy = np.concatenate([self.segments.reshape(-1, 2), self.triangles.reshape(-1, 2)])
        if len(xy) == 0:
            return None
        return xy.min(axis=0), xy.max(axis=0)

    def depth_range(self) -> tuple[float, float] | None:
        d = np.concatenate([self.seg_depth, self.tri_depth])
        return (float(d.min()), float(d.max())) if len(d) else None


def _chunks(counts: np.ndarray, size: int):
    """Split every curve into polylines of ``size`` segments (the last one of a curve may be shorter).

    Returns per chunk: first vertex, last vertex (global indices), root-to-tip parameter of its middle, curve index.
    """
    n_seg = counts - 1
    per_curve = -(-n_seg // size)
    curve = np.repeat(np.arange(len(counts)), per_curve)
    j = np.arange(per_curve.sum()) - np.repeat(np.cumsum(per_curve) - per_curve, per_curve)
    first = np.repeat(np.cumsum(counts) - counts, per_curve)
    start = first + j * size
    end = np.minimum(start + size, first + n_seg[curve])
    t = (0.5 * (start + end) - first) / np.maximum(n_seg[curve], 1)
    return start, end, t, curve


def _hash01(i: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random number in [0, 1) per integer (the same in every frame)."""
    x = (np.asarray(i, dtype=np.uint64) + np.uint64(0x9E3779B9)) * np.uint64(0x85EBCA6B)
    x ^= x >> np.uint64(13)
    x = x * np.uint64(0xC2B2AE35)
    x ^= x >> np.uint64(16)
    return (x & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def _mesh_list(meshes) -> list:
    """Normalise one frame's meshes: None, a (vertices, faces) pair, or a list of pairs."""
    if meshes is None:
        return []
    if isinstance(meshes, tuple) and len(meshes) >= 2 and np.asarray(meshes[1]).ndim == 2:
        return [meshes[:2]]
    return [m[:2] for m in meshes]


def _is_closed(faces: np.ndarray) -> bool:
    """True when every edge is shared by exactly two triangles (a watertight surface)."""
    if len(faces) == 0:
        return False
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def _signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _line_width(curve_count: int, panel_px: float) -> float:
    """Line width [pt]: thinner when many curves share the panel, so dense hair reads as hair and not as a blob."""
    return float(np.clip(0.9 * np.sqrt(800.0 / max(curve_count, 1)) * np.sqrt(panel_px / 500.0), 0.18, 1.6))


def _draw(ax, panel: _Panel, limits, depth_lo: float, depth_hi: float, line_width: float) -> None:
    from matplotlib.collections import PathCollection, PolyCollection

    (x0, x1), (y0, y1) = limits
    # The limits are fixed here, so collections are added without growing the data limits (autolim=False), which
    # walks every segment's path once more.
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_axis_off()
    span = max(depth_hi - depth_lo, 1e-12)
    seg_slice = np.clip(((panel.seg_depth - depth_lo) / span * DEPTH_SLICES).astype(np.int64), 0, DEPTH_SLICES - 1)
    tri_slice = np.clip(((panel.tri_depth - depth_lo) / span * DEPTH_SLICES).astype(np.int64), 0, DEPTH_SLICES - 1)
    depth01 = (panel.seg_depth - depth_lo) / span
    rgb = panel.seg_rgb * (1.0 - DEPTH_DARKEN * depth01)[:, None]
    # Translucent thin lines blend into a soft mass; thick ones stay opaque so their joints do not show as dots.
    alpha = 1.0 if line_width >= 0.6 else 0.85
    rgba = np.concatenate([rgb, np.full((len(rgb), 1), alpha)], axis=1)
    grey = np.clip(MESH_GREY * panel.tri_shade, 0.0, 1.0)
    tri_rgba = np.stack([grey, grey, grey * 0.98, np.ones_like(grey)], axis=1)
    for s in range(DEPTH_SLICES - 1, -1, -1):
        z = 2.0 * (DEPTH_SLICES - s)  # far slices first
        sel = np.flatnonzero(tri_slice == s)
        if len(sel):
            sel = sel[np.argsort(-panel.tri_depth[sel], kind="stable")]
            ax.add_collection(PolyCollection(panel.triangles[sel], facecolors=tri_rgba[sel], edgecolors=tri_rgba[sel],
                                             linewidths=0.3, antialiaseds=True, zorder=z),
                              autolim=False)
        sel = np.flatnonzero(seg_slice == s)
        if len(sel):
            sel = sel[np.argsort(-panel.seg_depth[sel], kind="stable")]
            paths, colors = _colour_paths(panel.segments[sel], rgba[sel])
            ax.add_collection(PathCollection(paths, facecolors="none", edgecolors=colors, linewidths=line_width,
                                             capstyle="round", joinstyle="round", antialiaseds=True, zorder=z + 1),
                              autolim=False)


def _colour_paths(polylines: np.ndarray, rgba: np.ndarray):
    """The polylines ``(P, n, 2)`` of one depth slice as one compound path per colour (``COLOUR_STEPS`` levels a
    channel), in the order their colours first come (far to near), and those colours: matplotlib's cost is per path
    (about 10 us), not per vertex."""
    from matplotlib.path import Path

    key = np.round(rgba[:, :3] * COLOUR_STEPS).astype(np.int64)
    key = (key[:, 0] * (COLOUR_STEPS + 1) + key[:, 1]) * (COLOUR_STEPS + 1) + key[:, 2]
    _, first, group = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # groups in the order of their first (farthest) polyline
    P, n = polylines.shape[:2]
    codes = np.full(n, Path.LINETO, dtype=Path.code_type)
    codes[0] = Path.MOVETO
    paths, colours = [], []
    by_group = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[by_group], np.arange(len(first) + 1))
    for g in order:
        members = by_group[bounds[g]:bounds[g + 1]]
        paths.append(Path(polylines[members].reshape(-1, 2), np.tile(codes, len(members))))
        colours.append(rgba[members[0]])
    return paths, np.asarray(colours)


def _limits(panels: list[_Panel], aspect: float, pad: float = 0.06):
    """Common x and y limits for panels of width/height ``aspect`` (data units per pixel equal in x and y)."""
    boxes = [b for b in (p.bounds() for p in panels) if b is not None]
    if not boxes:
        return (-1.0, 1.0), (-1.0 / aspect, 1.0 / aspect)
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    centre = 0.5 * (lo + hi)
    sx, sy = max(hi[0] - lo[0], 1e-9) * (1 + 2 * pad), max(hi[1] - lo[1], 1e-9) * (1 + 2 * pad)
    if sx / sy < aspect:
        sx = sy * aspect
    else:
        sy = sx / aspect
    return (centre[0] - sx / 2, centre[0] + sx / 2), (centre[1] - sy / 2, centre[1] + sy / 2)


def _depth_limits(panels: list[_Panel]) -> tuple[float, float]:
    ranges = [r for r in (p.depth_range() for p in panels) if r is not None]
    if not ranges:
        return 0.0, 1.0
    return min(r[0] for r in ranges), max(r[1] for r in ranges)


_CAPTION_BAND = 0.075
"""Fraction of the figure height kept under the panels for captions."""


def _sheet(panels: list[_Panel], titles, size_px, *, limits=None, depth=None):
    """A matplotlib Figure with the panels side by side (same camera and limits), each with its caption."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width, height = (int(v) for v in size_px)
    n = max(len(panels), 1)
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI, facecolor=BACKGROUND)
    FigureCanvasAgg(fig)
    margin = 0.012
    panel_w = (1.0 - margin * (n + 1)) / n
    panel_h = 1.0 - _CAPTION_BAND - margin
    aspect = (panel_w * width) / (panel_h * height)
    limits = limits or _limits(panels, aspect)
    depth_lo, depth_hi = depth or _depth_limits(panels)
    for i, panel in enumerate(panels):
        x0 = margin + i * (panel_w + margin)
        ax = fig.add_axes((x0, _CAPTION_BAND, panel_w, panel_h))
        ax.set_facecolor(BACKGROUND)
        line_width = _line_width(panel.curve_count, min(panel_w * width, panel_h * height))
        _draw(ax, panel, limits, depth_lo, depth_hi, line_width)
        if titles is not None and i < len(titles) and titles[i]:
            fig.text(x0 + 0.5 * panel_w, 0.5 * _CAPTION_BAND, str(titles[i]), ha="center", va="center",
                     fontsize=max(7.0, min(11.0, 0.022 * height)), color=CAPTION_COLOR, family="sans-serif")
        if i == 0:
            _draw_scale_bar(ax, limits, fontsize=max(7.0, min(10.0, 0.018 * height)))
    return fig


def scale_bar_length(span: float) -> float:
    """The scale bar's length [m] for a panel ``span`` metres wide: 1, 2 or 5 times a power of ten, the longest
    within a sixth of the span."""
    target = max(float(span), 1e-9) / 6.0
    power = 10.0 ** math.floor(math.log10(target))
    return max(m * power for m in (1.0, 2.0, 5.0) if m * power <= target * (1.0 + 1e-9))


def scale_bar_label(length: float) -> str:
    """``length`` [m] as a scale bar reads it: "5 mm", "10 cm", "1 m"."""
    for unit, size in (("m", 1.0), ("cm", 1e-2), ("mm", 1e-3)):
        if length >= size * (1.0 - 1e-9):
            return f"{length / size:g} {unit}"
    return f"{length / 1e-6:g} um"


def _draw_scale_bar(ax, limits, fontsize: float) -> None:
    """A bar of :func:`scale_bar_length` in the panel's lower left corner, its length written above it (the
    camera is orthographic: a metre is as long at every depth)."""
    (x0, x1), (y0, y1) = limits
    length = scale_bar_length(x1 - x0)
    left, base = x0 + 0.04 * (x1 - x0), y0 + 0.04 * (y1 - y0)
    tick = 0.012 * (y1 - y0)
    ax.plot([left, left, left, left + length, left + length, left + length],
            [base + tick, base - tick, base, base, base - tick, base + tick],
            color=CAPTION_COLOR, linewidth=1.0, solid_capstyle="butt", zorder=1000)
    ax.text(left + 0.5 * length, base + 2.0 * tick, scale_bar_label(length), ha="center", va="bottom",
            fontsize=fontsize, color=CAPTION_COLOR, family="sans-serif", zorder=1000)


def render_frames(frames, out_png, *, titles=None, meshes=None, view="three_quarter", size_px=(1600, 600),
                  max_curves: int = 4000) -> Path:
    """Draw a contact sheet: one panel per frame, side by side, with the same camera and limits in every panel.

    Args:
        frames: list of dicts, one per panel: curves prim name -> (points (N, 3) [m], curve_vertex_counts (C,)),
            world space, Z up, root first. Prims whose name contains "guide" are drawn in orange.
        out_png: the PNG to write (its folder is created).
        titles: optional caption per panel (default "frame i").
        meshes: optional list, one entry per frame: a (vertices (V, 3), faces (F, 3)) pair in world space, a list of
            such pairs, or None.
        view: a name from :data:`VIEWS` or (azimuth, elevation) in degrees.
        size_px: (width, height) of the picture in pixels.
        max_curves: curves drawn per panel at most; above it every k-th curve is drawn.

    Returns:
        The path of the PNG.

    Raises:
        PreviewWriteError: the PNG could not be written (nothing is left at ``out_png``).
    """
    out_png = Path(out_png)
    if meshes is not None and len(meshes) != len(frames):
        raise ValueError(f"{out_png}: {len(meshes)} mesh entries for {len(frames)} frames")
    cam = _camera(view)
    panels = [_Panel(f, None if meshes is None else meshes[i], cam, max_curves) for i, f in enumerate(frames)]
    if titles is None:
        titles = [f"frame {i}" for i in range(len(frames))]
    fig = _sheet(panels, titles, size_px)
    return _save(out_png, lambda stream: fig.savefig(stream, format="png", dpi=DPI, facecolor=BACKGROUND))


GRID_LABEL_PX = 190
"""Least width of the row-title column of :func:`render_grid` [px]; wider where a title needs it."""
GRID_LABEL_FONT_PT = 8
GRID_LABEL_INSET_PX = 8
"""Font size of the row titles and their distance from the picture's left edge (as much is kept on their right)."""
GRID_HEADER_PX = 30
"""Height of the column-title band of :func:`render_grid` [px]."""


def render_grid(rows, out_png, *, row_titles=None, col_titles=None, view="three_quarter", panel_px=(300, 300),
                max_curves: int = 2000, shared_limits: bool = True, row_colors=None) -> Path:
    """Draw a grid of panels: one row per run (a wedge variant, a shot), one column per frame.

    Args:
        rows: list of rows; a row is a list of frames, each a dict ``{"curves": {...}, "meshes": [...]}`` as
            :func:`render_frames` takes them (curves: prim name -> (points, counts); meshes: (vertices, faces)
            pairs, world space), or None for an empty panel (a run that stopped before that frame).
        out_png: the PNG to write (its folder is created).
        row_titles: a caption per row, drawn left of it (may hold several lines).
        col_titles: a caption per column, drawn above the grid.
        view: a name from :data:`VIEWS` or (azimuth, elevation) in degrees.
        panel_px: (width, height) of one panel in pixels.
        max_curves: curves drawn per panel at most.
        shared_limits: one camera framing and depth range for the whole grid (a wedge: looks compare
            directly), with a scale bar in the first panel; False frames each row on its own (shots of different
            scenes), with a scale bar in each row's first panel.
        row_colors: an optional text colour per row title (e.g. to mark runs that stopped on a fault).

    Returns:
        The path of the PNG.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out_png = Path(out_png)
    cam = _camera(view)
    n_rows = max(len(rows), 1)
    n_cols = max((len(r) for r in rows), default=1) or 1
    panels = [[None if f is None else _Panel(f["curves"], f.get("meshes"), cam, max_curves) for f in row]
              for row in rows]
    pw, ph = (int(v) for v in panel_px)
    label_px = _title_column_px(row_titles)
    width, height = label_px + n_cols * pw, GRID_HEADER_PX + n_rows * ph
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI, facecolor=BACKGROUND)
    FigureCanvasAgg(fig)
    pad = 4
    aspect = (pw - 2 * pad) / (ph - 2 * pad)
    everything = [p for row in panels for p in row if p is not None]
    limits = _limits(everything, aspect) if shared_limits else None
    depth = _depth_limits(everything) if shared_limits else None
    for r, row in enumerate(panels):
        present = [p for p in row if p is not None]
        row_limits = limits or _limits(present, aspect)
        lo, hi = depth or _depth_limits(present)
        top = height - GRID_HEADER_PX - r * ph
        if row_titles is not None and r < len(row_titles) and row_titles[r]:
            color = row_colors[r] if row_colors is not None and r < len(row_colors) and row_colors[r] else None
            fig.text(GRID_LABEL_INSET_PX / width, (top - ph / 2) / height, str(row_titles[r]), ha="left",
                     va="center", fontsize=GRID_LABEL_FONT_PT, color=color or CAPTION_COLOR, family="sans-serif",
                     linespacing=1.4)
        for c, panel in enumerate(row):
            rect = ((label_px + c * pw + pad) / width, (top - ph + pad) / height, (pw - 2 * pad) / width,
                    (ph - 2 * pad) / height)
            ax = fig.add_axes(rect)
            ax.set_facecolor(BACKGROUND)
            if panel is None:
                ax.set_axis_off()
                ax.text(0.5, 0.5, "not reached", ha="center", va="center", fontsize=8, color=CAPTION_COLOR,
                        transform=ax.transAxes)
                continue
            _draw(ax, panel, row_limits, lo, hi, _line_width(panel.curve_count, min(pw, ph)))
            if c == 0 and (r == 0 or not shared_limits):  # one scale for the grid, or one a row framed alone
                _draw_scale_bar(ax, row_limits, fontsize=7.0)
    for c in range(n_cols):
        if col_titles is not None and c < len(col_titles) and col_titles[c]:
            fig.text((label_px + (c + 0.5) * pw) / width, 1.0 - 0.5 * GRID_HEADER_PX / height, str(col_titles[c]),
                     ha="center", va="center", fontsize=9, color=CAPTION_COLOR, family="sans-serif")
    return _save(out_png, lambda stream: fig.savefig(stream, format="png", dpi=DPI, facecolor=BACKGROUND))


def _title_column_px(row_titles) -> int:
    """Width of the row-title column [px]: :data:`GRID_LABEL_PX`, or the widest title with its insets when wider
    (a wedged key in full, ``strands.bend_stiffness = 0.0001``, ran into the first panel)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    titles = [str(t) for t in (row_titles or ()) if t]
    if not titles:
        return GRID_LABEL_PX
    fig = Figure(dpi=DPI)
    renderer = FigureCanvasAgg(fig).get_renderer()
    widest = max(fig.text(0.0, 0.0, t, fontsize=GRID_LABEL_FONT_PT, family="sans-serif", linespacing=1.4)
                 .get_window_extent(renderer).width for t in titles)
    return max(GRID_LABEL_PX, int(np.ceil(widest)) + 2 * GRID_LABEL_INSET_PX)


def frame_title(frame: float, seconds: float) -> str:
    """A panel's caption: the frame's number in the cache (its time code) and its time from the first frame [s]."""
    label = f"{frame:g}" if float(frame).is_integer() else f"{frame:.2f}"
    return f"frame {label}   {seconds:.2f} s"


#: Most frames a contact sheet shows: its width is held to 2400 px (``sheet_size``), 200 px a panel at this count
#: (a sheet of 100 panels had none left to draw in). ``--gif`` shows every frame.
MAX_SHEET_FRAMES = 12


def sheet_size(panels: int) -> tuple[int, int]:
    """Pixel size of a contact sheet of ``panels`` frames (the run's preview and ``hairwarp preview`` alike)."""
    return (min(560 * panels, 2400), 600) if panels > 1 else (700, 700)


def cache_frames(cache_path) -> list[float]:
    """The frames of a cache a picture can show: its time samples (the start time code when it has none)."""
    from hairwarp.io.usd_common import _open_stage, _time_samples

    stage = _open_stage(cache_path)
    return _time_samples(stage) or [stage.GetStartTimeCode()]


def _pick_frames(cache_path, frames) -> list[float]:
    """Frame numbers to show: the listed ones, or ``frames`` evenly spaced time samples including the ends (every
    one when the cache has no more)."""
    if not isinstance(frames, int | np.integer):
        return [float(f) for f in frames]
    samples = cache_frames(cache_path)
    if frames >= len(samples):
        return samples
    idx = np.unique(np.round(np.linspace(0, len(samples) - 1, max(int(frames), 1))).astype(np.int64))
    return [samples[i] for i in idx]


def rendered_curves(curves: dict, guides: bool = False) -> dict:
    """The curves a preview draws: what renders, the dense hair, when the cache holds any besides its guides (as
    ``hairwarp run``'s own preview); every curve with ``guides`` (guides in orange) or when there is nothing else."""
    if guides:
        return curves
    dense = {name: c for name, c in curves.items() if "guide" not in name.lower()}
    return dense or curves


def preview_cache(cache_path, out_png=None, *, frames=4, gif=False, view="three_quarter", progress=False,
                  guides=False) -> Path:
    """Render a cache written by :class:`hairwarp.io.cache.CacheWriter` as a contact sheet PNG or an animated GIF.

    Args:
        cache_path: the USD cache.
        out_png: the picture to write, named ``.png`` (``.gif`` when ``gif``); default: beside the cache, same stem.
        frames: how many evenly spaced frames to show (first and last included; at most :data:`MAX_SHEET_FRAMES`,
            more are shown as that many), or a list of at most that many frame numbers.
        gif: write an animated GIF of every frame (at the cache's frame rate) instead of the contact sheet.
        view: a name from :data:`VIEWS` or (azimuth, elevation) in degrees.
        progress: show the GIF's frames drawn on stderr, as ``hairwarp run`` shows its frames.
        guides: draw the guide strands too (in orange); by default a cache with dense hair shows that alone, as
            ``hairwarp run``'s preview does (:func:`rendered_curves`).

    Returns:
        The path of the picture written.

    Raises:
        ValueError: ``out_png``'s suffix is not that of the format written (``.png``, or ``.gif`` with ``gif``), as
            a PNG written to ``y.jpg`` or a GIF to ``y.png`` would be misread by whatever opens it by its suffix.
        PreviewWriteError: the picture could not be written (nothing is left at its path).
    """
    from hairwarp.io.usd_inspect import read_frames

    cache_path = Path(cache_path)
    suffix = ".gif" if gif else ".png"
    out = Path(out_png) if out_png is not None else cache_path.with_suffix(suffix)
    if out.suffix.lower() != suffix:
        raise ValueError(f"{out}: the animation is a GIF; name the picture .gif (or leave --gif out for a PNG contact "
                         f"sheet)" if gif else f"{out}: the contact sheet is a PNG; name the picture .png (or add "
                         f"--gif for an animated GIF, named .gif)")
    if gif:
        return _write_gif(cache_path, out, view, progress, guides)
    if isinstance(frames, int | np.integer):
        frames = min(int(frames), MAX_SHEET_FRAMES)
    elif len(frames) > MAX_SHEET_FRAMES:
        raise ValueError(f"{len(frames)} frames: a contact sheet shows at most {MAX_SHEET_FRAMES} (a GIF shows every "
                         f"frame)")
    data = read_frames(cache_path, _pick_frames(cache_path, frames))
    return render_frames([rendered_curves(d["curves"], guides) for d in data], out,
                         titles=[frame_title(d["frame"], d["time"]) for d in data],
                         meshes=[[m[:2] for m in d["meshes"].values()] for d in data], view=view,
                         size_px=sheet_size(len(data)))


GIF_SIZE_PX = (520, 520)
GIF_MAX_CURVES = 2500


def gif_durations(count: int, fps: float) -> list[int]:
    """Per-frame display times [ms] of a GIF at ``fps``: GIF keeps hundredths of a second, so a constant 33 ms
    (30 fps) would play at 1/0.03 = 33 fps; the frames' ends are rounded to 10 ms instead, each from its exact time
    (3, 3, 4 hundredths at 30 fps), at least 20 ms a frame (browsers slow shorter ones down)."""
    step = 1000.0 / float(fps)
    ends = [10 * round(step * (i + 1) / 10.0) for i in range(count)]
    starts = [0] + ends[:-1]
    return [max(20, e - s) for s, e in zip(starts, ends)]


def _write_gif(cache_path: Path, out: Path, view, progress: bool = False, guides: bool = False) -> Path:
    """Every time sample as one GIF frame, all with the camera and limits of the whole animation.

    Drawing is most of the time (about 0.5 s a frame of the default scene's cache on a busy 2-core machine: building
    the line collections, then Agg); each frame's pixels are taken from the canvas, not through an encoded PNG.
    """
    from PIL import Image

    from hairwarp.io.usd_common import _open_stage
    from hairwarp.io.usd_inspect import read_frames
    from hairwarp.runner import _Progress

    fps = _open_stage(cache_path).GetTimeCodesPerSecond() or 24.0
    data = read_frames(cache_path)
    cam = _camera(view)
    panels = [_Panel(rendered_curves(d["curves"], guides), [m[:2] for m in d["meshes"].values()], cam,
                     GIF_MAX_CURVES) for d in data]
    width, height = GIF_SIZE_PX
    margin = 0.012
    aspect = ((1.0 - 2 * margin) * width) / ((1.0 - _CAPTION_BAND - margin) * height)
    limits = _limits(panels, aspect)
    depth = _depth_limits(panels)
    images = []
    shown = _Progress(len(data), progress)  # counts frames drawn, from 1: a 'frame 0/N' took the first tenth's line
    for done, (d, panel) in enumerate(zip(data, panels, strict=True), 1):
        fig = _sheet([panel], [frame_title(d["frame"], d["time"])], GIF_SIZE_PX, limits=limits, depth=depth)
        fig.canvas.draw()
        images.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())).convert("RGB"))
        shown.update(done)
    # One palette for the whole animation, from the first and last frames, so colours do not shimmer.
    probe = Image.new("RGB", (width, 2 * height))
    probe.paste(images[0], (0, 0))
    probe.paste(images[-1], (0, height))
    palette = probe.quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    frames = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    return _save(out, lambda stream: frames[0].save(stream, format="GIF", save_all=True, append_images=frames[1:],
                                                    duration=gif_durations(len(frames), fps), loop=0, optimize=False))
