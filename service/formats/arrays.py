"""``.npy`` and ``.npz`` files (numpy's own format; pickles are refused)."""

from __future__ import annotations

import lzma
import math
import os
import struct
import tokenize
import zipfile
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import BinaryIO, TypeVar

import numpy as np

from service.checks import MIN_POINTS, per_axis_problem
from service.formats.checks import MAX_ROW_BYTES, check_count, checked, xyz_columns, xyz_in_blocks
from service.formats.errors import InvalidPointsError, PointCloudFormatError

T = TypeVar("T")

NPZ_KEYS = ("points", "positions")  # the arrays of an .npz read, the first found: ours, Open3D's (o3d.t.io)
MAX_HEADER_BYTES = 10_000  # numpy's own limit (max_header_size), checked before numpy reads a header that long
# Largest .npz central directory read: zipfile makes a Python object of every entry, so a 57 MB archive listing
# 1,000,000 members took 494 MiB to open. np.savez of a few arrays writes under 100 bytes of it per array.
MAX_DIRECTORY_BYTES = 1 << 20
MAX_LISTED_KEYS = 20  # array names an error message lists


def read_npy(f: BinaryIO, max_points: int | None, size: int | None = None) -> np.ndarray:
    """``(N, >=3)`` or ``(1, N, >=3)`` numbers (the first three columns), or a structured array with x, y, z.

    ``size``: the bytes of the whole ``.npy`` file where ``f`` has no end to seek to (a member of an ``.npz``).
    """
    shape, fortran, dtype, rows = npy_layout(f, max_points, size)
    count = math.prod(shape)
    if dtype.names is None and not (shape[-1] == 3 and dtype == np.float64 and not fortran and _has_fileno(f)):
        try:  # numbers other than float64 [N, 3] in a file: only x, y, z are held, a block of rows at a time
            return checked(_xyz_table(f, dtype, rows, shape[-1], fortran))
        except OSError as exc:
            raise PointCloudFormatError(f"truncated or unreadable .npy file ({exc})") from None
    try:
        array = np.fromfile(f, dtype=dtype, count=count) if _has_fileno(f) else _from_stream(f, dtype, count)
    except (OSError, ValueError) as exc:
        raise PointCloudFormatError(f"truncated or unreadable .npy file ({exc})") from None
    if array.size != count:
        raise PointCloudFormatError(f"truncated .npy file: {array.size} of {count} values")
    array = array.reshape(shape, order="F" if fortran else "C")
    if dtype.names is not None:
        return xyz_columns([array[axis].reshape(-1) for axis in "xyz"])
    table = array.reshape(rows, shape[-1])  # [N, C]
    if table.shape[1] == 3 and table.dtype == np.float64 and table.flags.c_contiguous and table.flags.writeable:
        return checked(table)  # already what the readers return: no second 2,000,000-point copy
    return xyz_columns([table[:, axis] for axis in range(3)])


def npy_layout(
    f: BinaryIO, max_points: int | None, size: int | None = None
) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """The shape, Fortran order, dtype and points (rows) of the ``.npy`` file at ``f``'s position, left at its data,
    with :func:`read_npy`'s checks (the count limit, the bytes that follow, the row size) before any data is read.

    ``size``: as :func:`read_npy`'s.
    """
    shape, fortran, dtype = _header(f)
    rows = _rows(shape, dtype)
    check_count(rows, max_points)
    count = math.prod(shape)
    needed, held = count * dtype.itemsize, _bytes_left(f, size)
    if needed > held:  # before numpy allocates the array
        raise PointCloudFormatError(
            f"truncated .npy file: shape {list(shape)} of {dtype} needs {needed} bytes, {held} follow the header"
        )
    if math.prod(n for n in shape if n) * dtype.itemsize > np.iinfo(np.intp).max:  # empty, as (0, 2**63)
        raise PointCloudFormatError(f"not a valid .npy file (shape {list(shape)} is beyond any array's size)")
    row_bytes = count * dtype.itemsize // rows if rows else 0
    if row_bytes > MAX_ROW_BYTES:
        raise InvalidPointsError(
            f"rows of {row_bytes} bytes (shape {list(shape)} of {dtype}): at most {MAX_ROW_BYTES} "
            f"bytes per point, e.g. 16 float64 columns"
        )
    return shape, fortran, dtype, rows


def read_npz(f: BinaryIO, max_points: int | None) -> np.ndarray:
    """The array ``points`` of the archive, else ``positions`` (Open3D's tensor point clouds), else its only array
    (read as :func:`read_npy`)."""
    return _with_member(f, lambda stream, size: read_npy(stream, max_points, size))


def npy_count(f: BinaryIO) -> int:
    """The points (rows) the ``.npy`` header at ``f``'s position declares, with :func:`read_npy`'s header checks and
    errors; no data is read."""
    shape, _, dtype = _header(f)
    return _rows(shape, dtype)


def npz_count(f: BinaryIO) -> int:
    """The points the header of the ``.npz`` member :func:`read_npz` reads declares (:func:`npy_count`)."""
    return _with_member(f, lambda stream, size: npy_count(stream))


def _with_member(f: BinaryIO, use: Callable[[BinaryIO, int], T]) -> T:
    """``use(stream, size)`` of the archive's member that :func:`read_npz` reads (its bytes, uncompressed), the
    archive's errors as :class:`PointCloudFormatError`."""
    with opened_archive(f) as archive:
        member = cloud_member(archive)
        with archive.open(member) as stream:
            return use(stream, archive.getinfo(member).file_size)


@contextmanager
def opened_archive(f: BinaryIO) -> Iterator[zipfile.ZipFile]:
    """The ``.npz`` archive ``f`` open (closed afterwards; ``f`` left open), what opening it and reading its members
    raise as :class:`PointCloudFormatError` (:func:`archive_errors`)."""
    _check_directory(f)
    try:
        archive = zipfile.ZipFile(f)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:  # a zip version beyond 6.3
        raise PointCloudFormatError(f"not a valid .npz archive ({exc})") from None
    with archive, archive_errors():
        yield archive


def _check_directory(f: BinaryIO) -> None:
    """:class:`PointCloudFormatError` where the archive's central directory (its end record read as zipfile reads it)
    is larger than :data:`MAX_DIRECTORY_BYTES`, before zipfile parses an entry of it; ``f``'s position is kept."""
    position = f.tell()
    try:
        end = zipfile._EndRecData(f)  # the (ZIP64) end of central directory record; None: zipfile says what is wrong
    except (OSError, zipfile.BadZipFile):  # e.g. a ZIP64 locator naming several disks: zipfile.ZipFile says so below
        end = None
    finally:
        f.seek(position)
    if end is not None and end[zipfile._ECD_SIZE] > MAX_DIRECTORY_BYTES:
        raise PointCloudFormatError(
            f"not a usable .npz archive: its directory of members takes {end[zipfile._ECD_SIZE]} bytes, at most "
            f"{MAX_DIRECTORY_BYTES} are read (np.savez writes under 100 bytes per array)"
        )


def cloud_member(archive: zipfile.ZipFile) -> str:
    """The name of the member of ``archive`` that :func:`read_npz` reads: ``points.npy``, else ``positions.npy``,
    else its only ``.npy`` member."""
    names = [name for name in archive.namelist() if name.endswith(".npy")]
    named = [name for name in NPZ_KEYS if f"{name}.npy" in names]
    if named:
        return f"{named[0]}.npy"
    if len(names) == 1:
        return names[0]
    keys = [name[:-4] for name in names]
    more = len(keys) - MAX_LISTED_KEYS
    listed = f"{keys[:MAX_LISTED_KEYS]}" + (f" and {more} more" if more > 0 else "")
    raise PointCloudFormatError(
        f".npz archive has no array named {' or '.join(map(repr, NPZ_KEYS))} and not exactly one array: {listed}"
    )


@contextmanager
def archive_errors() -> Iterator[None]:
    """What reading an archive's members raises (a CRC error, a cut-off or corrupt member, a compression or an
    encryption) as :class:`PointCloudFormatError`."""
    try:
        yield
    except PointCloudFormatError:
        raise
    except (
        zipfile.BadZipFile,
        EOFError,
        OSError,
        ValueError,
        zlib.error,
        lzma.LZMAError,
        NotImplementedError,
        RuntimeError,
    ) as exc:
        raise PointCloudFormatError(f"corrupt or unsupported .npz archive ({type(exc).__name__}: {exc})") from None


def _header(f: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype]:
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            return np.lib.format.read_array_header_1_0(f)
        if version == (2, 0):
            _check_header_length(f)
            return np.lib.format.read_array_header_2_0(f)
        raise PointCloudFormatError(f"unsupported .npy format version {version}")
    except PointCloudFormatError:
        raise
    except (ValueError, EOFError, SyntaxError, OSError, TypeError, tokenize.TokenError, RecursionError):
        # what numpy's parsing of the header's Python literal lets through
        raise PointCloudFormatError("not a valid .npy file (unreadable header)") from None


def _check_header_length(f: BinaryIO) -> None:
    """A version 2.0 header is at most :data:`MAX_HEADER_BYTES` (numpy reads all 4 GiB its length may say first)."""
    position = f.tell()
    raw = f.read(4)
    f.seek(position)
    if len(raw) == 4 and struct.unpack("<I", raw)[0] > MAX_HEADER_BYTES:
        raise PointCloudFormatError(f"not a valid .npy file (a header of {struct.unpack('<I', raw)[0]} bytes)")


def _rows(shape: tuple[int, ...], dtype: np.dtype) -> int:
    if not all(type(n) is int and n >= 0 for n in shape):  # numpy lets negative numbers and booleans through
        raise PointCloudFormatError(f"not a valid .npy file (shape {shape})")
    if dtype.hasobject:
        raise InvalidPointsError("object arrays are refused (they would need pickle)")
    if dtype.names is not None:
        missing = [axis for axis in "xyz" if axis not in dtype.names]
        if missing:
            raise InvalidPointsError(f"structured array lacks fields {missing}")
        several = [axis for axis in "xyz" if dtype[axis].shape != ()]
        if several:
            raise InvalidPointsError(f"structured fields {several} are arrays; x, y and z must be single numbers")
        return math.prod(shape)
    if dtype.kind not in "fiu":
        raise InvalidPointsError(f"coordinates must be real numbers, got dtype {dtype} ({dtype.kind=})")
    sent = list(shape)  # as the caller sent it, for the messages
    if len(shape) == 3 and shape[0] == 1:
        shape = shape[1:]
    if len(shape) != 2 or shape[1] < 3:
        raise InvalidPointsError(f"expected shape [N, 3] (or [N, >3]: the first three columns), got {list(shape)}")
    # one row per axis: rows wider than any point's, or as many columns as a cloud needs points (3 or 4 rows are never
    # enough points, whatever the dtype's width)
    per_axis = shape[1] * dtype.itemsize > MAX_ROW_BYTES or shape[1] >= MIN_POINTS
    if shape[0] in (3, 4) and per_axis:  # [3, N], or [4, N]: homogeneous coordinates
        raise InvalidPointsError(per_axis_problem(sent))
    return int(shape[0])


def _bytes_left(f: BinaryIO, size: int | None) -> int:
    position = f.tell()
    if size is not None:
        return size - position
    end = f.seek(0, os.SEEK_END)
    f.seek(position)
    return end - position


def _has_fileno(f: BinaryIO) -> bool:
    try:
        f.fileno()
    except (OSError, AttributeError, ValueError):
        return False
    return True


def _xyz_table(f: BinaryIO, dtype: np.dtype, rows: int, columns: int, fortran: bool) -> np.ndarray:
    """``[N, 3]`` float64: the first three columns of the numeric ``[N, C]`` (or ``[1, N, C]``) array at ``f``'s
    position, read a block of ``BLOCK_BYTES`` at a time (C order) or as its first three columns (Fortran order), so
    that no more than the output and one block are held: an ``.npz`` member of 2,000,000 rows of 16 float64 columns
    held two copies of its 256 MB."""
    if rows == 0:  # however wide its rows (a row of 2 GiB is no numpy dtype): the empty cloud, refused as such
        return np.empty((0, 3), dtype=np.float64)
    if not fortran:
        return xyz_in_blocks(f, np.dtype((dtype, (columns,))), rows, "truncated .npy file")
    out = np.empty((rows, 3), dtype=np.float64)  # [N, 3]
    for axis in range(3):  # column after column: x, y and z are the first 3 N values
        out[:, axis] = _column(f, dtype, rows)
    return out


def _column(f: BinaryIO, dtype: np.dtype, count: int) -> np.ndarray:
    """The next ``count`` values of ``dtype`` at ``f``'s position (a view of the bytes read), or a format error."""
    data = f.read(count * dtype.itemsize)
    if len(data) != count * dtype.itemsize:
        raise PointCloudFormatError(f"truncated .npy file: {len(data) // dtype.itemsize} of {count} values follow")
    return np.frombuffer(data, dtype=dtype, count=count)


def _from_stream(f: BinaryIO, dtype: np.dtype, count: int) -> np.ndarray:
    data = f.read(count * dtype.itemsize)
    usable = len(data) - len(data) % dtype.itemsize
    return np.frombuffer(data, dtype=dtype, count=usable // dtype.itemsize)
