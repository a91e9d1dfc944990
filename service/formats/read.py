"""One reader for every entry point (CLI, HTTP uploads, the Python client): the format is found
from the content (:func:`service.formats.detect.detect`), never from the file name."""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from service.formats.arrays import npy_count, npz_count, read_npy, read_npz
from service.formats.checks import check_count
from service.formats.detect import HEAD_BYTES, MAX_HEAD_BYTES, detect, only_comments
from service.formats.e57 import e57_count, read_e57
from service.formats.errors import PointCloudFormatError, TooManyPointsError
from service.formats.las import las_count, read_las
from service.formats.leica import pts_count, ptx_count, read_pts, read_ptx
from service.formats.pcd import pcd_count, read_pcd
from service.formats.ply import ply_count, read_ply
from service.formats.text import read_text

Reader = Callable[[BinaryIO, "int | None"], np.ndarray]
READERS: dict[str, Reader] = {
    "ply": read_ply,
    "pcd": read_pcd,
    "las": read_las,
    "e57": read_e57,
    "npy": read_npy,
    "npz": read_npz,
    "pts": read_pts,
    "ptx": read_ptx,
    "text": read_text,
}
# The point count each format's header declares, from the readers' own header parsing (text: known only once read).
HEADER_COUNTS: dict[str, Callable[[BinaryIO], int]] = {
    "ply": ply_count,
    "pcd": pcd_count,
    "las": las_count,
    "npy": npy_count,
    "npz": npz_count,
    "e57": e57_count,
    "pts": pts_count,
    "ptx": ptx_count,
}
FROM_FILE = {"npz", "e57"}  # their headers are at their ends: an .npz's directory, an E57's XML section
# What check_declared_count reads of a file, its header within it (except FROM_FILE's, read from the file)
PRECHECK_BYTES = MAX_HEAD_BYTES
NEEDS_REAL_FILE = {"ply"}  # plyfile memory-maps binary data only from a file with a descriptor
READ_SUFFIXES = (  # conventional names
    ".ply",
    ".pcd",
    ".las",
    ".laz",
    ".e57",
    ".npy",
    ".npz",
    ".xyz",
    ".txt",
    ".csv",
    ".pts",
    ".ptx",
)


def read_cloud(
    source: str | os.PathLike[str] | bytes | BinaryIO, name: str | None = None, max_points: int | None = None
) -> np.ndarray:
    """Finite float64 ``[N, 3]`` coordinates (``N >= 1``) of the cloud in ``source``.

    ``source``: a path, the file's bytes, or a seekable binary file (read from its current position).
    ``max_points``: more points than this (known from the header before the points are read, for
    text while reading) raise :class:`TooManyPointsError`.

    Raises:
        PointCloudFormatError: with ``name`` (default: the path's name) and the reason; its subclasses
            carry the HTTP status (``InvalidPointsError`` 422, ``TooManyPointsError`` 413,
            ``MissingReaderError`` 415, others 400).
        OSError: a path that cannot be opened.
    """
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        with open(path, "rb") as f:
            return read_cloud(f, name or path.name, max_points)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return read_cloud(io.BytesIO(source), name, max_points)
    name = name or "<cloud>"
    try:
        start = source.tell()
        kind = detect_at(source)
        source.seek(start)
        if kind in NEEDS_REAL_FILE and not _has_fileno(source):
            with tempfile.TemporaryFile() as spooled:
                shutil.copyfileobj(source, spooled)
                spooled.seek(0)
                return READERS[kind](spooled, max_points)
        return READERS[kind](source, max_points)
    except PointCloudFormatError as exc:
        raise _named(exc, name) from None


def check_declared_count(source: BinaryIO, name: str, max_points: int) -> None:
    """:class:`TooManyPointsError` (named as :func:`read_cloud` names it) where the header of the cloud at ``source``
    declares more than ``max_points`` points: PLY's vertex count, PCD's ``POINTS``, the LAS/LAZ point count, an
    ``.npy``'s shape, an ``.npz`` member's, the record counts of an E57's scans (its XML section, parsed by expat, not
    the e57 library), a PTS file's first count, a PTX file's first columns x rows. Only the header is read (from the
    first :data:`PRECHECK_BYTES`; an ``.npz``'s directory and member header and an E57's XML section from the
    file), ``source``'s position is kept, and nothing else is
    refused here: text formats (counted only while read), a header this cannot read whole, and every other problem
    are :func:`read_cloud`'s to find, which stays the authority: it checks the count again, and reads no more points
    than the header declares (a header declaring fewer than its data holds gives that many, but for LAS/LAZ, whose
    reader refuses a count its data does not hold)."""
    start = source.tell()
    try:
        kind = detect_at(source)
        count_of = HEADER_COUNTS.get(kind)
        if count_of is None:
            return
        source.seek(start)
        count = count_of(source if kind in FROM_FILE else io.BytesIO(source.read(PRECHECK_BYTES)))
        check_count(count, max_points)
    except TooManyPointsError as exc:
        raise _named(exc, name) from None
    except PointCloudFormatError:
        return  # read_cloud says what is wrong, and in what order
    finally:
        source.seek(start)


def detect_at(source: BinaryIO) -> str:
    """The format of the file at ``source``'s position (:func:`detect`), from its first bytes (read, not put back)."""
    head = source.read(HEAD_BYTES)
    while only_comments(head) and len(head) < MAX_HEAD_BYTES and (more := source.read(len(head))):
        head += more  # a PCD header after many comment lines
    return detect(head)


def _named(exc: PointCloudFormatError, name: str) -> PointCloudFormatError:
    """``exc`` with ``name: `` before its message, same class and attributes."""
    exc.args = (f"{name}: {exc.args[0] if exc.args else exc}", *exc.args[1:])
    return exc


def _has_fileno(f: BinaryIO) -> bool:
    try:
        f.fileno()
    except (OSError, AttributeError, ValueError, io.UnsupportedOperation):
        return False
    return True
