"""AMD TressFX files: hair strands (``.tfx``, binary) and collision meshes (``.tfxmesh``, text).

Both are Y up; :func:`read_tfx` and :func:`read_tfxmesh` return Z-up data with
:data:`hairwarp.groom.Y_UP_TO_Z_UP` ((x, y, z) -> (x, -z, y), a proper rotation, so windings are kept).
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from hairwarp.colliders import TfxMeshError
from hairwarp.groom import Groom, GroomError, _read_bytes, _up_matrix

__all__ = ["read_tfx", "read_tfxmesh"]


_TFX_HEADER = struct.Struct("<f7I32I")  # version, counts, 5 offsets, 32 reserved = 160 bytes
_TFX_VERSION = 4.0


def read_tfx(path, *, min_length: float = 1e-3, up_axis: str = "y") -> Groom:
    """Reads an AMD TressFX 4 ``.tfx`` hair file.

    Layout (little-endian): ``float version`` (4.0), ``uint32 numHairStrands``,
    ``uint32 numVerticesPerStrand``, then byte offsets of the vertex positions, strand UVs, vertex
    UVs, strand thickness and vertex colours (0 = absent), and 32 reserved uint32 (160 bytes).
    Positions are ``float4`` per vertex, strand after strand, root first; ``w = 0`` marks a pinned
    vertex and ``w = 1`` a free one. Only the positions are read. The assets are Y up; they are
    turned to Z up with :data:`Y_UP_TO_Z_UP`. Lengths are taken as metres.

    Args:
        path: the ``.tfx`` file.
        min_length: strands shorter than this are dropped with one warning [m].
        up_axis: the file's up axis, ``"y"`` (TressFX's) or ``"z"``.

    Returns:
        The groom, with ``root_uv`` and ``root_normal`` from :meth:`Groom.with_projected_roots`.

    Raises:
        GroomError: naming the file: truncated or corrupt header or data, an unsupported version, or
            a strand whose vertex 0 is not pinned.
    """
    p = Path(path)
    rot = _up_matrix(up_axis, str(p))
    data = _read_bytes(p)
    size = len(data)
    if size < _TFX_HEADER.size:
        raise GroomError(f"{p}: truncated TressFX file: {size} bytes, the header alone is {_TFX_HEADER.size}")
    header = _TFX_HEADER.unpack_from(data, 0)
    version, n_strands, n_verts, off_pos, off_suv, off_vuv, off_thick, off_col = header[:8]
    if not (math.isfinite(version) and abs(version - _TFX_VERSION) < 1e-6):
        raise GroomError(f"{p}: unsupported TressFX version {version!r} (expected {_TFX_VERSION})")
    if n_strands < 1 or n_verts < 2:
        raise GroomError(f"{p}: corrupt TressFX header: {n_strands} strands of {n_verts} vertices")
    blocks = {
        "vertex positions": (off_pos, n_strands * n_verts * 16),
        "strand UVs": (off_suv, n_strands * 8),
        "vertex UVs": (off_vuv, n_strands * n_verts * 8),
        "strand thickness": (off_thick, n_strands * 4),
        "vertex colours": (off_col, n_strands * n_verts * 16),
    }
    if off_pos == 0:
        raise GroomError(f"{p}: corrupt TressFX header: no vertex positions")
    for name, (offset, nbytes) in blocks.items():
        if offset == 0:
            continue
        if offset < _TFX_HEADER.size or offset % 4:
            raise GroomError(f"{p}: corrupt TressFX header: {name} offset {offset}")
        if offset + nbytes > size:
            raise GroomError(
                f"{p}: truncated TressFX file: {name} need bytes {offset}..{offset + nbytes}, the file has {size}"
            )
    xyzw = np.frombuffer(data, dtype="<f4", count=n_strands * n_verts * 4, offset=off_pos)
    xyzw = xyzw.reshape(n_strands, n_verts, 4).astype(np.float64)
    if not np.isfinite(xyzw).all():
        g, v = (int(i) for i in np.argwhere(~np.isfinite(xyzw).all(axis=2))[0])
        raise GroomError(f"{p}: strand {g} vertex {v} is not finite ({', '.join(f'{x:g}' for x in xyzw[g, v])})")
    unpinned = np.flatnonzero(xyzw[:, 0, 3] != 0.0)
    if unpinned.size:
        raise GroomError(
            f"{p}: strand {int(unpinned[0])} has no pinned root (w of vertex 0 = {xyzw[unpinned[0], 0, 3]:g}, "
            f"expected 0); {unpinned.size} such strands"
        )
    xyz = xyzw[:, :, :3]
    if rot is not None:
        xyz = xyz @ rot.T
    groom = Groom.from_polylines(list(xyz), min_length=min_length, source=str(p))
    return groom.with_projected_roots()


def read_tfxmesh(path) -> Any:
    """Read a TressFX collision mesh (``.tfxmesh``, text) as a Z-up ``trimesh.Trimesh``.

    The file is Y-up; points are turned to Z-up by (x, y, z) -> (x, -z, y), a proper rotation, so the
    face winding (outward) is kept. Normals and skinning weights in the file are not used.

    Args:
        path: the ``.tfxmesh`` file.

    Returns:
        The mesh, not processed (vertex order and count as in the file).

    Raises:
        TfxMeshError: missing or malformed sections, counts that do not match, indices out of range,
            non-finite coordinates.
    """
    import trimesh

    path = Path(path)
    try:
        # the format is ASCII numbers; a comment in another encoding (a Latin-1 byte) is no reason to refuse the file
        raw = path.read_bytes().decode("utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise TfxMeshError(f"{path}: cannot read ({exc})") from exc
    lines = [(n + 1, line.split()) for n, line in enumerate(raw) if line.strip() and not line.lstrip().startswith("#")]
    pos = 0

    def section(key: str, width: int):
        nonlocal pos
        if pos >= len(lines) or len(lines[pos][1]) != 2 or lines[pos][1][0] != key:
            where = f"line {lines[pos][0]}" if pos < len(lines) else "end of file"
            raise TfxMeshError(f"{path}: expected '{key} <count>' at {where}")
        line_no, (_, count_text) = lines[pos]
        try:
            count = int(count_text)
        except ValueError:
            raise TfxMeshError(f"{path}: line {line_no}: bad count {count_text!r}") from None
        rows = lines[pos + 1:pos + 1 + count]
        if count < 0 or len(rows) != count:
            raise TfxMeshError(f"{path}: line {line_no}: {key} {count} but {len(rows)} entries follow")
        pos += 1 + count
        if width == 0:
            return None
        bad = next((r for r in rows if len(r[1]) != width), None)
        if bad is not None:
            raise TfxMeshError(f"{path}: line {bad[0]}: expected {width} fields, got {len(bad[1])}")
        try:
            return np.array([r[1] for r in rows], dtype=float).reshape(count, width)
        except ValueError as exc:
            raise TfxMeshError(f"{path}: {key} block: non-numeric entry ({exc})") from None

    section("numOfBones", 0)
    vertices = section("numOfVertices", 15)
    triangles = section("numOfTriangles", 4)
    points = vertices[:, 1:4]
    if not np.all(np.isfinite(points)):
        first = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise TfxMeshError(f"{path}: vertex {first} is not finite ({', '.join(f'{x:g}' for x in points[first])}) "
                           f"in the file")
    faces = triangles[:, 1:4]
    if len(faces) == 0 or len(points) == 0:
        raise TfxMeshError(f"{path}: no vertices or no triangles")
    if np.any(faces != np.round(faces)) or faces.min() < 0 or faces.max() >= len(points):
        raise TfxMeshError(f"{path}: triangle vertex indices must be integers in [0, {len(points)})")
    z_up = np.stack([points[:, 0], -points[:, 2], points[:, 1]], axis=1)
    return trimesh.Trimesh(vertices=z_up, faces=faces.astype(np.int64), process=False)
