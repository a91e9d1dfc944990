"""PLY (ascii, binary little and big endian) with ``plyfile``: the vertex element's x, y, z.

Other vertex properties (colours, normals, intensity) and other elements (faces) are ignored.
Binary files are memory-mapped by ``plyfile``, so the caller passes a real file (one with a
``fileno``); triangle faces are mapped too, other faces are read row by row. An ASCII file whose first
element is the vertex element of scalar properties (as most writers make it) has its vertex rows parsed by
``numpy.loadtxt`` (about 12x faster than ``plyfile``'s Python loop), each value cast to its declared type as
``plyfile`` casts it; other ASCII files are read by ``plyfile``. The header is parsed
from its first :data:`MAX_HEADER_BYTES` at most, and the rows every element declares are checked
against the bytes after the header before ``plyfile`` allocates them.
"""

from __future__ import annotations

import io
import os
import warnings
from types import ModuleType
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from service.formats.checks import as_declared, check_count, check_line_lengths, xyz_columns
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError

if TYPE_CHECKING:
    from plyfile import PlyData, PlyElement

MAX_HEADER_BYTES = 256 * 1024  # plyfile parses a header one byte at a time (about 1.5 us a byte)


def read_ply(f: BinaryIO, max_points: int | None) -> np.ndarray:
    plyfile = require("plyfile", "reading PLY files")
    start = f.tell()
    head = io.BytesIO(f.read(MAX_HEADER_BYTES))
    try:
        header = plyfile.PlyData._parse_header(head)  # the header only: the counts before any allocation
    except (plyfile.PlyParseError, ValueError, UnicodeDecodeError) as exc:
        if len(head.getbuffer()) == MAX_HEADER_BYTES and "early end-of-file" in str(exc):
            raise PointCloudFormatError(f"invalid PLY header (no end_header in its first {MAX_HEADER_BYTES} bytes)") \
                from None
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
    _check_rows_fit(plyfile, header, f.seek(0, os.SEEK_END) - start - head.tell())
    if header.text:
        f.seek(start + head.tell())
        check_line_lengths(f, "PLY ASCII data")
    if header.text and header.elements[0].name == "vertex" and not any(
            isinstance(prop, plyfile.PlyListProperty) for prop in vertex.properties):
        f.seek(start + head.tell())
        return _ascii_vertices(f, vertex)
    triangles = {element.name: {prop.name: 3 for prop in element.properties
                                if isinstance(prop, plyfile.PlyListProperty)} for element in header}
    data = _read(plyfile, f, start, triangles)
    try:
        return xyz_columns([np.asarray(data["vertex"][axis]) for axis in "xyz"])
    finally:
        del data


def _ascii_vertices(f: BinaryIO, vertex: PlyElement) -> np.ndarray:
    """x, y, z of the ``vertex.count`` ASCII rows at ``f``'s position (``vertex``: plyfile's element of scalar
    properties), each cast to its property's declared type."""
    names = [prop.name for prop in vertex.properties]
    columns = [names.index(axis) for axis in "xyz"]
    text = io.TextIOWrapper(f, encoding="ascii", errors="strict", newline=None)
    try:
        with warnings.catch_warnings():  # numpy warns of blank lines (not counted as rows) and of no rows at all
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(text, dtype=np.float64, usecols=columns, max_rows=vertex.count, ndmin=2,
                               comments=None)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PointCloudFormatError(f"corrupt PLY data ({exc})") from None
    finally:
        text.detach()  # the caller's file stays open
    if len(table) != vertex.count:
        raise PointCloudFormatError(f"corrupt PLY data: {len(table)} vertex rows, the header says {vertex.count}")
    kinds = {prop.name: prop for prop in vertex.properties}
    return xyz_columns([as_declared(table[:, k], np.dtype(kinds[axis].dtype()), f"PLY vertex {axis}")
                        for k, axis in enumerate("xyz")])


def _check_rows_fit(plyfile: ModuleType, header: PlyData, body: int) -> None:
    """Refuse counts whose rows cannot fit in the ``body`` bytes after the header, before ``plyfile`` allocates
    an array of each element's count: a row takes at least one byte, in ASCII one per property (a value), in
    binary the sizes of its scalars and list lengths."""
    need = 0
    for element in header:
        if element.count < 0:
            raise PointCloudFormatError(f"invalid PLY header (element '{element.name}' has count {element.count})")
        if header.text:
            row = len(element.properties)
        else:
            row = sum(np.dtype(prop.list_dtype()[0] if isinstance(prop, plyfile.PlyListProperty) else prop.dtype())
                      .itemsize for prop in element.properties)
        need += element.count * max(1, row)
        if need > body:
            raise PointCloudFormatError(
                f"PLY header declares {element.count} '{element.name}' rows: with the elements before them at least "
                f"{need} bytes, but {body} bytes follow the header"
            )


def _read(plyfile: ModuleType, f: BinaryIO, start: int, known_list_len: dict):
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
