"""Cem Yuksel's ``.hair`` files (http://www.cemyuksel.com/cyCodeBase/soln/using_hair_files.html), read and
written as grooms: metres, Z up unless told otherwise (the format records neither)."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from hairwarp.groom import Groom, GroomError, _read_bytes, _up_matrix

__all__ = ["read_hair", "write_hair"]


_HAIR_HEADER = struct.Struct("<4sIIIIff3f88s")  # 128 bytes
_HAIR_SEGMENTS, _HAIR_POINTS, _HAIR_THICKNESS, _HAIR_TRANSPARENCY, _HAIR_COLORS = 1, 2, 4, 8, 16


def read_hair(path, *, min_length: float = 1e-3, up_axis: str = "z") -> Groom:
    """Reads Cem Yuksel's ``.hair`` file (http://www.cemyuksel.com/cyCodeBase/soln/using_hair_files.html).

    Header (128 bytes, little-endian): ``"HAIR"``, ``uint32`` hair count, ``uint32`` point count,
    ``uint32`` bit array (1 segments, 2 points, 4 thickness, 8 transparency, 16 colours present),
    ``uint32`` default segments, ``float`` default thickness, ``float`` default transparency,
    ``float[3]`` default colour, ``char[88]`` file info. Then, for each bit set in that order:
    ``uint16`` segments per hair, ``float[3]`` per point, ``float`` thickness per point, ``float``
    transparency per point, ``float[3]`` colour per point. The format has no units or up axis; we
    read metres, Z up unless ``up_axis="y"``. Only the points are kept.

    Raises:
        GroomError: naming the file: a wrong signature, no points, inconsistent counts, or a file
            shorter than its header says.
    """
    p = Path(path)
    rot = _up_matrix(up_axis, str(p))
    data = _read_bytes(p)
    size = len(data)
    if size < _HAIR_HEADER.size:
        raise GroomError(f"{p}: truncated .hair file: {size} bytes, the header alone is {_HAIR_HEADER.size}")
    sig, n_hair, n_points, bits, d_segments = _HAIR_HEADER.unpack_from(data, 0)[:5]
    if sig != b"HAIR":
        raise GroomError(f"{p}: not a .hair file (signature {sig!r}, expected b'HAIR')")
    if not bits & _HAIR_POINTS:
        raise GroomError(f"{p}: .hair file without points (bit array {bits:#x})")
    if n_hair < 1:
        raise GroomError(f"{p}: .hair file with no hairs")
    offset = _HAIR_HEADER.size
    if bits & _HAIR_SEGMENTS:
        if offset + 2 * n_hair > size:
            raise GroomError(f"{p}: truncated .hair file: segment array needs {2 * n_hair} bytes at {offset}")
        segments = np.frombuffer(data, dtype="<u2", count=n_hair, offset=offset).astype(np.int64)
        offset += 2 * n_hair
    else:
        segments = np.full(n_hair, d_segments, dtype=np.int64)
    short = np.flatnonzero(segments < 1)
    if short.size:
        raise GroomError(f"{p}: strand {int(short[0])} has {int(segments[short[0]])} segments")
    counts = segments + 1
    if int(counts.sum()) != n_points:
        raise GroomError(f"{p}: corrupt .hair file: segments give {int(counts.sum())} points, the header {n_points}")
    if offset + 12 * n_points > size:
        raise GroomError(
            f"{p}: truncated .hair file: points need {12 * n_points} bytes at {offset}, the file has {size}"
        )
    pts = np.frombuffer(data, dtype="<f4", count=3 * n_points, offset=offset).reshape(n_points, 3).astype(np.float64)
    offset += 12 * n_points
    for bit, width, name in (
        (_HAIR_THICKNESS, 4, "thickness"),
        (_HAIR_TRANSPARENCY, 4, "transparency"),
        (_HAIR_COLORS, 12, "colour"),
    ):
        if bits & bit:
            offset += width * n_points
            if offset > size:
                raise GroomError(f"{p}: truncated .hair file: the {name} array runs past the end ({size} bytes)")
    if rot is not None:
        pts = pts @ rot.T
    strands = np.split(pts, np.cumsum(counts)[:-1])
    groom = Groom.from_polylines(strands, min_length=min_length, source=str(p))
    return groom.with_projected_roots()


def write_hair(path, groom: Groom, *, thickness=None, info: str = "") -> None:
    """Writes a groom as Cem Yuksel's ``.hair`` file: segments and points, and thickness if given.

    Coordinates are written as stored (metres, Z up), as float32. The file is written beside its
    target and renamed into place, so a failed write leaves no partial file.

    Args:
        path: the file to write.
        groom: the strands; each may have at most 65,536 points (uint16 segment counts).
        thickness: None (default thickness 0 in the header), a number (the header default), one value per
            strand, or one value per point (all strands' points in order) [m].
        info: up to 88 bytes of file information (UTF-8, truncated).

    Raises:
        GroomError: a strand with too many points or a thickness of the wrong size.
    """
    p = Path(path)
    counts = np.array([len(a) for a in groom.strands], dtype=np.int64)
    too_long = np.flatnonzero(counts - 1 > 0xFFFF)
    if too_long.size:
        raise GroomError(f"{p}: strand {int(too_long[0])} has {int(counts[too_long[0]])} points; .hair allows 65536")
    n_points = int(counts.sum())
    bits = _HAIR_SEGMENTS | _HAIR_POINTS
    default_thickness = 0.0
    per_point = None
    if thickness is not None:
        t = np.asarray(thickness, dtype=np.float64)
        if t.ndim == 0:
            default_thickness = float(t)
        elif t.shape == (groom.strand_count,):
            per_point = np.repeat(t, counts)
        elif t.shape == (n_points,):
            per_point = t
        else:
            raise GroomError(
                f"{p}: thickness must be a number, ({groom.strand_count},) per strand or ({n_points},) per point, "
                f"got shape {t.shape}"
            )
        if per_point is not None:
            bits |= _HAIR_THICKNESS
    header = _HAIR_HEADER.pack(
        b"HAIR",
        groom.strand_count,
        n_points,
        bits,
        0,
        default_thickness,
        0.0,
        1.0,
        1.0,
        1.0,
        info.encode("utf-8")[:88],
    )
    body = [
        header,
        (counts - 1).astype("<u2").tobytes(),
        np.concatenate(groom.strands).astype("<f4").tobytes(),
    ]
    if per_point is not None:
        body.append(per_point.astype("<f4").tobytes())
    tmp = p.with_name(p.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(b"".join(body))
        os.replace(tmp, p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise GroomError(f"{p}: cannot write ({exc.strerror or exc})") from None
