"""PCD (ascii, binary, binary_compressed) with ``pypcd4``: the x, y, z fields.

The header is parsed once, here (``pypcd4.MetaData``), so that the point count, the record type and the
body's size (the compressed block's declared sizes) are checked before anything is allocated; ``pypcd4``
then reads the data that follows it. Other fields are ignored.

An organized cloud (``HEIGHT`` > 1: a depth image's grid) marks a pixel without a return by a point whose x, y and
z are all NaN, as PCL does; such points are left out (``pcl::removeNaNFromPointCloud``), the others keep their order.
Any other NaN or Inf is refused, as in every other file (``docs/decisions/0067-organized-pcd-missing-returns.md``).
"""

from __future__ import annotations

import io
import os
import struct
import warnings
from types import ModuleType
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from service.formats.checks import (
    BLOCK_BYTES,
    FLOAT32_MAX,
    as_declared,
    check_count,
    check_text_lines,
    checked,
    stacked_xyz,
    xyz_in_blocks,
)
from service.formats.deps import require
from service.formats.detect import MAX_HEAD_BYTES
from service.formats.errors import InvalidPointsError, PointCloudFormatError

if TYPE_CHECKING:
    from pypcd4 import MetaData

MAX_HEADER_LINES = 64
MAX_LINE_BYTES = 4096
MAX_VALUES_PER_POINT = 4096  # the sum of COUNT; pypcd4 makes a record field of each value (SHOT1344 has 1353)
LZF_MAX_RATIO = 88  # an LZF back reference of 3 bytes repeats at most 264
# The binary_compressed block is one LZF stream, expanded whole before x, y and z are taken: at most this many bytes
# (2,000,000 records of 64 bytes, or fewer wider ones: FPFH33 descriptors beside x, y, z are 144 bytes). 2,000,000
# records of 128 bytes took 472 MiB above idle.
MAX_COMPRESSED_BLOCK_BYTES = 128 << 20
ROWS_PER_BLOCK = BLOCK_BYTES // 24  # float64 x, y, z rows an organized cloud's missing returns are left out of at once


def read_pcd(f: BinaryIO, max_points: int | None) -> np.ndarray:
    pypcd4 = require("pypcd4", "reading PCD files")
    require("lzf", "reading PCD files")  # pypcd4 imports it for binary_compressed
    meta = read_metadata(pypcd4, f)
    check_count(meta.points, max_points)
    if meta.width * meta.height != meta.points:  # as PCL's reader refuses it
        raise PointCloudFormatError(f"invalid PCD header (WIDTH {meta.width} x HEIGHT {meta.height} = "
                                    f"{meta.width * meta.height} points, but POINTS says {meta.points})")
    missing = [axis for axis in "xyz" if axis not in meta.fields]
    if missing:
        raise InvalidPointsError(f"PCD file lacks fields {missing}")
    dtype = point_record(meta)
    several = [axis for axis in "xyz" if meta.count[meta.fields.index(axis)] != 1]
    if several:
        raise InvalidPointsError(f"PCD fields {several} have COUNT > 1; x, y and z must be single values")
    _check_body(f, meta, dtype)
    try:
        if meta.data == "ascii" and meta.points > 0:
            return _usable(_ascii_xyz(f, meta.points, dtype), meta)
        if meta.data == "binary_compressed" and meta.points > 0:
            return _usable(_compressed_xyz(f, meta.points, dtype), meta)
        if meta.data == "binary":  # a block of records at a time, only x, y, z kept
            return _usable(xyz_in_blocks(f, dtype, meta.points, "corrupt PCD data: binary records"), meta)
        table = pypcd4.pypcd4._parse_pc_data(f, meta)  # no points, or pypcd4's binaryscompressed spelling
    except PointCloudFormatError:
        raise
    except Exception as exc:  # what numpy, struct and lzf raise on bad data
        raise PointCloudFormatError(f"corrupt PCD data ({type(exc).__name__}: {exc})") from None
    table = np.atleast_1d(table)
    if len(table) != meta.points:
        raise PointCloudFormatError(f"PCD data holds {len(table)} points; the header says {meta.points}")
    return _usable(stacked_xyz([np.asarray(table[axis]).reshape(-1) for axis in "xyz"]), meta)


def pcd_count(f: BinaryIO) -> int:
    """The points (``POINTS``) the PCD header at ``f``'s position declares, with :func:`read_pcd`'s header errors; no
    data is read."""
    return read_metadata(require("pypcd4", "reading PCD files"), f).points


def _usable(xyz: np.ndarray, meta: MetaData) -> np.ndarray:
    """The checked points of ``xyz [N, 3]`` (a fresh array), an organized cloud's missing returns left out."""
    if meta.height > 1 and len(xyz):
        xyz = _without_missing_returns(xyz, meta.width, meta.height)
    return checked(xyz)


def _without_missing_returns(xyz: np.ndarray, width: int, height: int) -> np.ndarray:
    """``xyz [N, 3]`` without the points whose x, y and z are all NaN, the others in their order: moved up in place,
    ``ROWS_PER_BLOCK`` rows at a time (no second copy of a multi-million-point cloud), and returned as ``[K, 3]``, a
    view of ``xyz``. :class:`InvalidPointsError` naming the first other point with a NaN, an Inf or a value beyond
    float32 (by its index in the file and its place in the ``width`` x ``height`` grid), or where no point is left."""
    kept, bad, first_bad = 0, 0, -1  # rows kept so far; rows of other non-finite values, the first one's index
    for begin in range(0, len(xyz), ROWS_PER_BLOCK):
        block = xyz[begin:begin + ROWS_PER_BLOCK]  # [n, 3] a view
        missing = np.isnan(block).all(axis=1)  # [n]
        wrong = ~missing & ~(np.abs(block) <= FLOAT32_MAX).all(axis=1)  # [n] NaN compares false
        if wrong.any() and first_bad < 0:
            first_bad = begin + int(np.argmax(wrong))
        bad += int(wrong.sum())
        if bad:  # only counted from here on
            continue
        if missing.any() or kept < begin:
            valid = block[~missing] if missing.any() else block  # [v, 3] a copy of the block's points, or the block
            xyz[kept:kept + len(valid)] = valid  # numpy copies through a buffer where the two overlap
        kept += len(block) - int(missing.sum())
    grid = f"the organized cloud ({width} x {height})"
    if bad:
        where = f" (row {first_bad // width}, column {first_bad % width})" if width else ""
        raise InvalidPointsError(
            f"{bad} point(s) of {grid} with NaN/Inf coordinates or beyond the float32 range, first at index "
            f"{first_bad}{where}; only points whose x, y and z are all NaN are missing returns, which are left out"
        )
    if kept == 0:
        raise InvalidPointsError(f"{grid} has no valid point: all {len(xyz)} are missing returns (x, y and z NaN)")
    return xyz[:kept]


def _ascii_xyz(f: BinaryIO, points: int, dtype: np.dtype) -> np.ndarray:
    """x, y, z of the ``points`` ASCII rows at ``f``'s position (each of one value per field, checked by
    :func:`_check_body`), each cast to its field's type (as pypcd4's typed parse reads them), without the other fields
    or any row past ``points`` (pypcd4 parsed every field of every row: 25,000 rows of 4,096 values took 0.8 GB,
    40,000,000 rows under a header of 1,000 points 0.9 GB)."""
    columns = [dtype.names.index(axis) for axis in "xyz"]  # each value is a column (COUNT > 1: one per value)
    text = io.TextIOWrapper(f, encoding="ascii", errors="strict", newline=None)
    try:
        with warnings.catch_warnings():  # numpy warns of no rows at all
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(text, dtype=np.float64, usecols=columns, max_rows=points, ndmin=2)  # on whitespace
    except (ValueError, UnicodeDecodeError) as exc:
        raise PointCloudFormatError(f"corrupt PCD data ({exc})") from None
    finally:
        text.detach()  # the caller's file stays open
    if len(table) != points:
        raise PointCloudFormatError(f"PCD data holds {len(table)} points; the header says {points}")
    return stacked_xyz([as_declared(table[:, k], dtype[axis], f"PCD field {axis}") for k, axis in enumerate("xyz")])


def _compressed_xyz(f: BinaryIO, points: int, dtype: np.dtype) -> np.ndarray:
    """x, y, z of the binary_compressed block at ``f``'s position (sizes checked by :func:`_check_body`): LZF
    decompressed once, each field's ``points`` values one after another in the record's order, x, y and z taken as
    views of it (pypcd4 also filled a zeroed record array of every field: twice the block's size)."""
    import lzf

    compressed, raw = struct.unpack("<II", f.read(8))
    block = lzf.decompress(f.read(compressed), raw)
    if block is None or len(block) != raw:
        raise PointCloudFormatError(f"corrupt PCD data: the binary_compressed block does not expand to {raw} bytes")
    offsets, offset = {}, 0
    for name in dtype.names:  # fields in the record's order, COUNT > 1 as one field per value
        offsets[name] = offset
        offset += dtype[name].itemsize * points
    return stacked_xyz([np.frombuffer(block, dtype=dtype[axis], count=points, offset=offsets[axis]) for axis in "xyz"])


def read_metadata(pypcd4: ModuleType, f: BinaryIO) -> MetaData:
    """``pypcd4``'s header of the PCD file at ``f``'s position, read a bounded line at a time; ``f`` is left at the
    data."""
    lines: list[str] = []
    start = f.tell()
    while len(lines) < MAX_HEADER_LINES and f.tell() - start <= MAX_HEAD_BYTES:  # comments count in bytes only
        raw = f.readline(MAX_LINE_BYTES)
        if not raw:
            break
        if len(raw) == MAX_LINE_BYTES and not raw.endswith(b"\n"):
            raise PointCloudFormatError(f"invalid PCD header (a line longer than {MAX_LINE_BYTES} bytes)")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointCloudFormatError("invalid PCD header (not ASCII text)") from None
        if line and not line.startswith("#"):
            lines.append(line)
            if line.upper().startswith("DATA"):
                break
    if not lines or not lines[-1].upper().startswith("DATA"):  # pypcd4 would take binary_compressed for it
        raise PointCloudFormatError(f"invalid PCD header (no DATA line in its first {MAX_HEADER_LINES} entries and "
                                    f"{MAX_HEAD_BYTES} bytes)")
    encodings = [encoding.value for encoding in pypcd4.Encoding]  # ascii, binary, binary_compressed and an alias
    if lines[-1].split()[1:2] not in [[encoding] for encoding in encodings]:
        raise PointCloudFormatError(f"invalid PCD header ({lines[-1][:80]!r}: DATA must be one of {encodings})")
    try:  # without VERSION, which PCL's reader ignores: pypcd4 takes only 0.7, PCL wrote .5 and .6 headers alike
        return pypcd4.MetaData.parse_header([line for line in lines if line.split()[0].upper() != "VERSION"])
    except Exception as exc:  # pydantic's ValidationError: a missing or malformed header entry
        raise PointCloudFormatError(f"invalid PCD header ({_reason(exc)})") from None


def _reason(exc: Exception) -> str:
    """What is wrong, in one line: each pydantic error as ``field: message`` (no pydantic URL), else the message."""
    errors = getattr(exc, "errors", None)
    if callable(errors):
        return "; ".join(f"{'.'.join(map(str, e['loc'])) or 'header'}: {e['msg']}" for e in errors())[:300]
    return " ".join(str(exc).split())[:300]


def point_record(meta: MetaData) -> np.dtype:
    """The numpy record of a point, from FIELDS, SIZE, TYPE and COUNT, once they are known to agree."""
    entries = {"FIELDS": meta.fields, "SIZE": meta.size, "TYPE": meta.type, "COUNT": meta.count}
    if len({len(values) for values in entries.values()}) != 1:
        sizes = ", ".join(f"{key} {len(values)}" for key, values in entries.items())
        raise PointCloudFormatError(f"invalid PCD header (FIELDS, SIZE, TYPE and COUNT differ in length: {sizes})")
    if sum(meta.count) > MAX_VALUES_PER_POINT:
        raise PointCloudFormatError(
            f"invalid PCD header (COUNT adds up to {sum(meta.count)} values per point; at most {MAX_VALUES_PER_POINT})"
        )
    try:
        return meta.build_dtype()
    except (KeyError, ValueError, TypeError) as exc:  # TYPE F SIZE 2; a field named twice
        raise PointCloudFormatError(f"invalid PCD header (no record type for its fields: {exc!r})") from None


def _check_body(f: BinaryIO, meta: MetaData, dtype: np.dtype) -> None:
    """The bytes after the header hold the points the header declares (checked before pypcd4 allocates them); ASCII
    data, no line too long for numpy's text reader and each declared row of one value per field (counted on whitespace
    as PCL splits them: only x, y, z are parsed), in one pass."""
    if meta.data == "ascii":
        check_text_lines(f, "PCD ascii data", meta.points, len(dtype.names), "corrupt PCD data")
        return
    if meta.points == 0:
        return
    start = f.tell()
    body = f.seek(0, os.SEEK_END) - start
    f.seek(start)
    expected = meta.points * dtype.itemsize
    if meta.data == "binary":
        if body < expected:
            raise PointCloudFormatError(f"PCD binary data holds {body} bytes; the header's {meta.points} points "
                                        f"need {expected}")
        return
    if expected > MAX_COMPRESSED_BLOCK_BYTES:  # its compressed size does not bound what it expands to
        raise InvalidPointsError(f"PCD binary_compressed data of {meta.points} records of {dtype.itemsize} bytes "
                                 f"expands to {expected} bytes, at most {MAX_COMPRESSED_BLOCK_BYTES} are read at once; "
                                 "save it as binary, or without extra fields")
    sizes = f.read(8)
    f.seek(start)
    if len(sizes) != 8:
        raise PointCloudFormatError("PCD binary_compressed data cut short")
    compressed, raw = struct.unpack("<II", sizes)
    if raw != expected:
        raise PointCloudFormatError(f"PCD binary_compressed block declares {raw} bytes; the fields need {expected}")
    if compressed > body - 8 or raw > compressed * LZF_MAX_RATIO:
        raise PointCloudFormatError(f"PCD binary_compressed block of {compressed} bytes (with {body - 8} in the "
                                    f"file) cannot expand to the {raw} bytes it declares")
