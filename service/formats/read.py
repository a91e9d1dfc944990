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

from service.formats.arrays import read_npy, read_npz
from service.formats.detect import HEAD_BYTES, MAX_HEAD_BYTES, detect, only_comments
from service.formats.errors import PointCloudFormatError
from service.formats.las import read_las
from service.formats.pcd import read_pcd
from service.formats.ply import read_ply
from service.formats.text import read_text

Reader = Callable[[BinaryIO, "int | None"], np.ndarray]
READERS: dict[str, Reader] = {
    "ply": read_ply, "pcd": read_pcd, "las": read_las, "npy": read_npy, "npz": read_npz, "text": read_text,
}
NEEDS_REAL_FILE = {"ply"}  # plyfile memory-maps binary data only from a file with a descriptor
READ_SUFFIXES = (".ply", ".pcd", ".las", ".laz", ".npy", ".npz", ".xyz", ".txt", ".csv")  # conventional names


def read_cloud(source: str | os.PathLike[str] | bytes | BinaryIO, name: str | None = None,
               max_points: int | None = None) -> np.ndarray:
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
        head = source.read(HEAD_BYTES)
        while only_comments(head) and len(head) < MAX_HEAD_BYTES and (more := source.read(len(head))):
            head += more  # a PCD header after many comment lines
        kind = detect(head)
        source.seek(start)
        if kind in NEEDS_REAL_FILE and not _has_fileno(source):
            with tempfile.TemporaryFile() as spooled:
                shutil.copyfileobj(source, spooled)
                spooled.seek(0)
                return READERS[kind](spooled, max_points)
        return READERS[kind](source, max_points)
    except PointCloudFormatError as exc:
        raise _named(exc, name) from None


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
