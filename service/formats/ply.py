"""PLY (ascii, binary little and big endian): the vertex element's x, y, z; ``plyfile`` parses the header.

Other vertex properties (colours, normals, intensity) and other elements (faces) are never read: binary vertex rows
are read a block at a time from where the elements before them end (their rows must have a fixed size: an element of
lists before the vertices is refused), ASCII vertex rows by ``numpy.loadtxt`` after one line per row of the elements
before them, each value cast to its declared type as ``plyfile`` casts it. (``plyfile`` read every element, faces
that are not triangles row by row in Python: 3,000,000 of them took 23 s and 0.9 GB.) The header is parsed from its
first :data:`MAX_HEADER_BYTES` at most, and the rows every element declares are checked against the bytes after the
header first. Vertex elements with list properties are refused.
"""

from __future__ import annotations

import io
import itertools
import os
import warnings
from types import ModuleType
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from service.formats.checks import as_declared, check_count, check_text_lines, checked, xyz_columns, xyz_in_blocks
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError

if TYPE_CHECKING:
    from plyfile import PlyData, PlyElement

MAX_HEADER_BYTES = 256 * 1024  # plyfile parses a header one byte at a time (about 1.5 us a byte)
ASCII_BLOCK_ROWS = 1 << 16  # ASCII vertex rows parsed at a time: only x, y, z of each block are kept
# ASCII values parsed at a time (rows x properties): numpy's reader returns every property as float64, so a block of
# ASCII_BLOCK_ROWS rows of a vertex with thousands of one-digit properties took several times its text at once
ASCII_BLOCK_VALUES = 1 << 21


def read_ply(f: BinaryIO, max_points: int | None) -> np.ndarray:
    plyfile = require("plyfile", "reading PLY files")
    header, body = read_header(plyfile, f)  # body: where the elements' rows begin
    vertex = header["vertex"]
    check_count(vertex.count, max_points)
    kinds = {prop.name: prop for prop in vertex.properties}
    missing = [axis for axis in "xyz" if axis not in kinds]
    if missing:
        raise InvalidPointsError(f"PLY vertex element lacks properties {missing}")
    if any(isinstance(kinds[axis], plyfile.PlyListProperty) for axis in "xyz"):
        raise InvalidPointsError("PLY vertex x, y, z must be scalar properties, not lists")
    if any(isinstance(prop, plyfile.PlyListProperty) for prop in vertex.properties):
        raise InvalidPointsError("PLY vertex element with list properties: only scalar vertex properties are read")
    _check_rows_fit(plyfile, header, f.seek(0, os.SEEK_END) - body)
    before = header.elements[:[element.name for element in header.elements].index("vertex")]
    f.seek(body)
    if header.text:  # one line per row of every element
        check_text_lines(f, "PLY ASCII data")
        return _ascii_vertices(f, vertex, skip=sum(element.count for element in before))
    lists = [element.name for element in before
             if any(isinstance(prop, plyfile.PlyListProperty) for prop in element.properties)]
    if lists:  # rows of lists have no fixed size: the vertex rows' place would take reading them all
        raise InvalidPointsError(f"binary PLY whose vertex element follows an element of lists ({lists[0]!r}): "
                                 "only files with their vertices before such elements are read")
    f.seek(body + sum(element.count * row_record(element, header.byte_order).itemsize for element in before))
    record = row_record(vertex, header.byte_order)
    return checked(xyz_in_blocks(f, record, vertex.count, "corrupt PLY data: vertex rows"))


def ply_count(f: BinaryIO) -> int:
    """The vertices the PLY header at ``f``'s position declares, with :func:`read_ply`'s header errors; no rows are
    read."""
    return read_header(require("plyfile", "reading PLY files"), f)[0]["vertex"].count


def read_header(plyfile: ModuleType, f: BinaryIO) -> tuple[PlyData, int]:
    """``plyfile``'s header at ``f``'s position (parsed from its first :data:`MAX_HEADER_BYTES` at most; it has a
    vertex element) and the offset of the first row after it."""
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
    return header, start + head.tell()


def row_record(element: PlyElement, byte_order: str) -> np.dtype:
    """The numpy record of one row of ``element`` (scalar properties only), in the file's byte order."""
    return np.dtype([(prop.name, prop.dtype(byte_order)) for prop in element.properties])


def _ascii_vertices(f: BinaryIO, vertex: PlyElement, skip: int = 0) -> np.ndarray:
    """x, y, z of the ``vertex.count`` ASCII rows at ``f``'s position after ``skip`` rows of the elements before them
    (``vertex``: plyfile's element of scalar properties), each cast to its property's declared type. Blank lines are no
    rows, and every vertex row must hold one value per property (else a face row could pass for a vertex)."""
    names = [prop.name for prop in vertex.properties]
    text = io.TextIOWrapper(f, encoding="ascii", errors="strict", newline=None)
    try:
        skipped = 0
        while skipped < skip:  # the rows of the elements before the vertices, one line each
            line = text.readline()
            if not line:
                raise PointCloudFormatError(f"corrupt PLY data: {skipped} of the {skip} rows before the vertices")
            skipped += bool(line.strip())
        columns = [names.index(axis) for axis in "xyz"]
        block_rows = max(1, min(ASCII_BLOCK_ROWS, ASCII_BLOCK_VALUES // len(names)))
        table = np.empty((vertex.count, 3))  # [N, 3]: x, y, z only; the other properties are dropped block by block
        rows = 0
        with warnings.catch_warnings():  # numpy warns of no rows at all
            warnings.simplefilter("ignore", UserWarning)
            while rows < vertex.count:
                # at most as many lines as rows are missing: the rows of the elements after the vertices stay unread
                lines = list(itertools.islice(text, min(vertex.count - rows, block_rows)))
                if not lines:
                    break  # the end of the file
                block = np.loadtxt([line for line in lines if line.strip()], dtype=np.float64, ndmin=2,
                                   comments=None)  # [n, P]; blank lines are no rows
                if len(block) and block.shape[1] != len(names):
                    raise PointCloudFormatError(f"corrupt PLY data: vertex rows of {block.shape[1]} values, the "
                                                f"header declares {len(names)} properties")
                table[rows:rows + len(block)] = block[:, columns] if len(block) else block.reshape(0, 3)
                rows += len(block)
    except (ValueError, UnicodeDecodeError) as exc:  # rows of different lengths among them
        raise PointCloudFormatError(f"corrupt PLY data ({exc})") from None
    finally:
        text.detach()  # the caller's file stays open
    if rows != vertex.count:
        raise PointCloudFormatError(f"corrupt PLY data: {rows} vertex rows, the header says {vertex.count}")
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
