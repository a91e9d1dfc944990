"""PLY (ascii, binary little and big endian) with ``plyfile``: the vertex element's x, y, z.

Other vertex properties (colours, normals, intensity) and other elements (faces) are ignored.
Binary files are memory-mapped by ``plyfile``, so the caller passes a real file (one with a
``fileno``); triangle faces are mapped too, other faces are read row by row.
"""

from __future__ import annotations

from typing import BinaryIO

import numpy as np

from service.formats.checks import check_count, xyz_columns
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError


def read_ply(f: BinaryIO, max_points: int | None) -> np.ndarray:
    plyfile = require("plyfile", "reading PLY files")
    start = f.tell()
    try:
        header = plyfile.PlyData._parse_header(f)  # the header only: the counts before any allocation
    except (plyfile.PlyParseError, ValueError, UnicodeDecodeError) as exc:
        raise PointCloudFormatError(f"invalid PLY header ({exc})") from None
    if "vertex" not in header:
        raise InvalidPointsError("PLY file has no vertex element")
    vertex = header["vertex"]
    check_count(vertex.count, max_points)
    kinds = {prop.name: prop for prop in vertex.properties}
    missing = [axis for axis in "xyz" if axis not in kinds]
    if missing:
        raise InvalidPointsError(f"PLY vertex element lacks properties {missing}")
    if any(isinstance(kinds[axis], plyfile.PlyListProperty) for axis in "xyz"):
        raise InvalidPointsError("PLY vertex x, y, z must be scalar properties, not lists")
    triangles = {element.name: {prop.name: 3 for prop in element.properties
                                if isinstance(prop, plyfile.PlyListProperty)} for element in header}
    data = _read(plyfile, f, start, triangles)
    try:
        return xyz_columns([np.asarray(data["vertex"][axis]) for axis in "xyz"])
    finally:
        del data


def _read(plyfile, f: BinaryIO, start: int, known_list_len: dict):
    try:
        f.seek(start)
        try:
            return plyfile.PlyData.read(f, mmap="c", known_list_len=known_list_len)
        except plyfile.PlyElementParseError as exc:
            if "unexpected list length" not in str(exc):
                raise
            f.seek(start)  # faces that are not all triangles: read them row by row
            return plyfile.PlyData.read(f, mmap="c")
    except (plyfile.PlyParseError, ValueError, UnicodeDecodeError, OSError) as exc:
        raise PointCloudFormatError(f"corrupt PLY data ({exc})") from None
